"""Exact plane cuts of tetrahedral meshes and Nanson's deformed area."""

import math
from pathlib import Path

import basix.ufl
import dolfinx
import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import meshio
import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI

from hyper.fem import section

CYLINDER = Path(__file__).resolve().parents[1] / "meshes" / "muscle-cylinder" / "muscle-cylinder.msh"


def close(a, b, rtol=1e-12):
    return abs(a - b) <= rtol * abs(b)


def cut_area(mesh, origin, normal):
    return section.CutSection(mesh, origin, normal).area0()


def cylinder_mesh(comm):
    """The project's cylinder (radius 0.02 m, length 0.1 m), read with meshio on rank 0."""
    cells, x = np.zeros((0, 4), np.int64), np.zeros((0, 3))
    if comm.rank == 0:
        msh = meshio.read(CYLINDER)
        cells = np.vstack([c.data for c in msh.cells if c.type == "tetra"]).astype(np.int64)
        x = msh.points
    element = basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,))
    return dolfinx.mesh.create_mesh(comm, cells, element, x)


def polygon_area(points):
    """Shoelace area of points in a plane z = const, star-shaped about the z axis."""
    angle = np.arctan2(points[:, 1], points[:, 0])
    p = points[np.argsort(angle)]
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def lateral_section(mesh, z0):
    """The corners of the cylinder's section at z0, from its boundary alone: where the
    edges of the exterior facets cross the plane (or the boundary vertices on it)."""
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 2, facets)
    x = mesh.geometry.x
    on = np.unique(nodes[np.abs(x[nodes, 2] - z0) < 1e-15])
    edges = np.unique(np.sort(np.concatenate([nodes[:, [0, 1]], nodes[:, [1, 2]], nodes[:, [0, 2]]]), axis=1), axis=0)
    za, zb = x[edges[:, 0], 2] - z0, x[edges[:, 1], 2] - z0
    crossing = edges[(za * zb < 0) & (np.abs(za) > 1e-15) & (np.abs(zb) > 1e-15)]
    a, b = x[crossing[:, 0]], x[crossing[:, 1]]
    t = (z0 - a[:, 2]) / (b[:, 2] - a[:, 2])
    return np.concatenate([x[on], a + t[:, None] * (b - a)])


# --- numpy kernels -----------------------------------------------------------------------


@pytest.mark.parametrize("degree", [1, 2, 4, 6])
def test_triangle_rule_exact_and_symmetric(degree):
    bary, w = section.triangle_rule(degree)
    assert close(w.sum(), 1.0, 1e-14) and np.allclose(bary.sum(axis=1), 1.0, atol=1e-15)
    # ∫ x^a y^b over the reference triangle (area 1/2) = a! b! / (a + b + 2)!
    x, y = bary[:, 1], bary[:, 2]
    for a in range(degree + 1):
        for b in range(degree + 1 - a):
            exact = math.factorial(a) * math.factorial(b) / math.factorial(a + b + 2)
            assert close(0.5 * w @ (x**a * y**b), exact, 1e-13)
    # Symmetric: the points are invariant under permutations of the corners, weights too.
    key = lambda b, w: sorted(zip(np.round(b, 12).tolist(), np.round(w, 12).tolist()))  # noqa: E731
    assert key(bary, w) == key(bary[:, [1, 2, 0]], w) == key(bary[:, [1, 0, 2]], w)


def test_cut_single_tetrahedron_cases():
    tet = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    e3 = np.array([0.0, 0, 1])
    # One vertex above: a triangle, scaled copy of the base by 1 - z.
    cells, tri = section.cut_triangles(tet, [0, 0, 0.25], e3)
    assert cells.tolist() == [0] and close(section.triangle_areas(tri).sum(), 0.5 * 0.75**2)
    # The base face lies in the plane: it belongs to the cell above the plane only.
    assert close(section.triangle_areas(section.cut_triangles(tet, [0, 0, 0], e3)[1]).sum(), 0.5)
    assert len(section.cut_triangles(tet, [0, 0, 0], -e3)[0]) == 0
    # Three vertices above: the section x = 1/2 is a triangle of legs 1/2.
    cells, tri = section.cut_triangles(tet, [0.5, 0, 0], [-1.0, 0, 0])
    assert close(section.triangle_areas(tri).sum(), 0.125)
    # Two vertices above: x + y = 1/2 cuts a rectangle, √2/2 long and 1/2 high.
    cells, tri = section.cut_triangles(tet, [0.25, 0.25, 0], np.array([1.0, 1, 0]) / math.sqrt(2))
    assert cells.tolist() == [0, 0] and close(section.triangle_areas(tri).sum(), math.sqrt(2) / 4)
    # Plane through vertex 0 and the midpoints of edges 1-3 and 2-3: the quadrilateral
    # case with one corner on the plane, area |(e1 + e3)/2 × (e2 + e3)/2| / 2.
    n = np.array([1.0, 1.0, -1.0]) / math.sqrt(3.0)
    cells, tri = section.cut_triangles(tet, [0, 0, 0], n)
    exact = 0.5 * np.linalg.norm(np.cross([0.5, 0, 0.5], [0, 0.5, 0.5]))
    assert close(section.triangle_areas(tri).sum(), exact)


def test_principal_plane_finds_the_long_axis():
    rng = np.random.default_rng(1)
    box = rng.uniform([-1, -2, -7], [3, 2, 13], size=(4000, 3))
    origin, normal = section.principal_plane(box)
    assert np.allclose(origin, box.mean(axis=0), rtol=0, atol=1e-12)
    assert np.allclose(normal, [0, 0, 1], atol=0.05)
    # Rotated, the axis rotates with it (sign: largest component positive).
    c, s = math.cos(0.4), math.sin(0.4)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    _, turned = section.principal_plane(box @ rot.T)
    assert np.allclose(turned, rot @ normal, atol=1e-12)
    # Bitwise the same whatever the order of the points.
    o2, n2 = section.principal_plane(rng.permutation(box))
    assert np.array_equal(o2, origin) and np.array_equal(n2, normal)


def test_principal_plane_of_a_box_mesh():
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 2, 5]], [2, 3, 6])
    origin, normal = section.principal_plane(section.global_vertices(mesh))
    assert np.allclose(origin, [0.5, 1.0, 2.5], atol=1e-14)
    assert np.allclose(normal, [0, 0, 1], atol=1e-14)


def graded_box(n=6):
    """Tetrahedra (6 a hexahedron) filling [0, 2] x [0, 1] x [0, 1], with the vertex planes
    along x crowded toward x = 0 (x = 2 s²): the vertices' mean is far from the centroid."""
    s = np.linspace(0.0, 1.0, n + 1)
    across = np.linspace(0.0, 1.0, 4)
    x, y, z = np.meshgrid(2 * s**2, across, across, indexing="ij")
    points = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    index = np.arange(len(points)).reshape(x.shape)
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets = []
    for i in range(n):
        for j in range(3):
            for k in range(3):
                corner = [index[i + a, j + b, k + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
                tets += [[corner[v] for v in t] for t in kuhn]
    return points, np.array(tets)


def test_solid_plane_is_the_centroid_and_inertia_axis_whatever_the_vertices():
    points, tets = graded_box()
    volume, first, second = section.solid_moments(points[tets])
    assert close(volume, 2.0)
    # The box's second moments about the origin: ∫x² = 8/3, ∫y² = ∫z² = 2/3, ∫xy = 1, ∫yz = 1/2.
    assert np.allclose(first, [2.0, 1.0, 1.0], rtol=1e-13)
    assert np.allclose(second, [[8 / 3, 1, 1], [1, 2 / 3, 0.5], [1, 0.5, 2 / 3]], rtol=1e-13)
    origin, normal = section.inertia_plane(volume, first, second)
    assert np.allclose(origin, [1.0, 0.5, 0.5], atol=1e-14)
    assert np.allclose(normal, [1, 0, 0], atol=1e-14)
    vertex_origin, _ = section.principal_plane(points)
    assert vertex_origin[0] < 0.8  # the vertices' mean follows the crowding: 2 mean(s²) = 0.72
    # The solid's plane halves the volume; its cut is the box's 1 x 1 section.
    _, tri = section.cut_triangles(points[tets], origin, normal)
    assert close(section.triangle_areas(tri).sum(), 1.0)


def test_solid_plane_of_a_box_mesh_on_any_ranks():
    mesh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 2, 5]], [2, 3, 6])
    origin, normal = section.solid_plane(mesh)
    assert np.allclose(origin, [0.5, 1.0, 2.5], atol=1e-13)
    assert np.allclose(normal, [0, 0, 1], atol=1e-13)


def prism_surface(around=48, radius=20.0, length=100.0):
    """A closed, outward regular 48-gon prism along z (a cylinder as an STL has it)."""
    phi = 2 * np.pi * np.arange(around) / around
    ring = np.column_stack([radius * np.cos(phi), radius * np.sin(phi)])
    points = np.vstack([np.column_stack([ring, np.zeros(around)]), np.column_stack([ring, np.full(around, length)]),
                        [[0, 0, 0], [0, 0, length]]])
    bottom, top = 2 * around, 2 * around + 1
    tris = []
    for i in range(around):
        j = (i + 1) % around
        tris += [[i, j, j + around], [i, j + around, i + around], [bottom, j, i], [top, around + i, around + j]]
    return points, np.array(tris)


def test_a_surface_gives_its_solid_moments_and_exact_cuts():
    points, tris = prism_surface()
    polygon = 0.5 * 48 * 20.0**2 * math.sin(2 * math.pi / 48)
    shift = np.array([300.0, -40.0, 700.0])  # far from the coordinates' origin, as a Visible Human muscle is
    volume, first, second = section.surface_solid_moments(points + shift, tris)
    assert close(volume, polygon * 100.0, 1e-13)
    origin, normal = section.inertia_plane(volume, first, second)
    assert np.allclose(origin, shift + [0, 0, 50], rtol=0, atol=1e-9)
    assert np.allclose(normal, [0, 0, 1], atol=1e-12)
    for z in (50.0, 3.0, 97.5):
        assert close(section.surface_cut_area(points, tris, [0, 0, z], [0, 0, -1]), polygon, 1e-12)
    # Tilted by 30° about x through the middle, the plane still crosses the sides only: area / cos 30°.
    tilted = [0, -math.sin(math.radians(30)), math.cos(math.radians(30))]
    assert close(section.surface_cut_area(points, tris, [0, 0, 50], tilted), polygon / math.cos(math.radians(30)),
                 1e-12)
    assert section.surface_cut_area(points, tris, [0, 0, 150], [0, 0, 1]) == 0.0


# --- exact cut areas ------------------------------------------------------------------------


def test_unit_cube_axis_plane_through_vertices():
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 4, 4, 4)
    for normal in ([0, 0, 1], [0, 0, -1]):
        assert close(cut_area(mesh, [0.5, 0.5, 0.5], normal), 1.0)
    assert close(cut_area(mesh, [0.25, 0.0, 0.0], [1, 0, 0]), 1.0)
    assert close(cut_area(mesh, [0.0, 0.3, 0.0], [0, 1, 0]), 1.0)  # between vertices


@pytest.mark.parametrize("n", [3, 4])
def test_unit_cube_oblique_plane(n):
    # x + y + z = 3/2 cuts the cube in a regular hexagon whose corners are the midpoints
    # of six edges, e.g. (1, 1/2, 0) and (1, 0, 1/2): side s = √2/2, area (3√3/2) s² = 3√3/4.
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, n, n, n)
    area = cut_area(mesh, [0.5, 0.5, 0.5], np.ones(3) / math.sqrt(3.0))
    assert close(area, 3.0 * math.sqrt(3.0) / 4.0)


@pytest.mark.parametrize("z0", [0.05, 0.0314, 0.08])
def test_cylinder_equals_its_boundary_polygon(z0):
    # z0 = 0.05 is the meshed mid-section: vertices lie on it (some one rounding step off).
    mesh = cylinder_mesh(MPI.COMM_SELF)
    corners = lateral_section(mesh, z0)
    area = cut_area(mesh, [0, 0, z0], [0, 0, 1])
    assert close(area, polygon_area(corners))
    assert 0.95 < area / (math.pi * 0.02**2) < 1.0  # a polygon inscribed in the circle


# --- Nanson ----------------------------------------------------------------------------------


def displacement(mesh, expr):
    V = fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    u = fem.Function(V)
    u.interpolate(expr)
    return u


def test_deformed_area_affine():
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 3, 3, 3)
    G = np.array([[0.10, -0.05, 0.02], [0.03, 0.20, -0.04], [0.01, 0.06, -0.15]])
    u = displacement(mesh, lambda x: G @ x)
    F = np.eye(3) + G
    for normal in (np.array([0.0, 0, 1]), np.ones(3) / math.sqrt(3.0)):
        cut = section.CutSection(mesh, [0.5, 0.5, 0.5], normal)
        exact = cut.area0() * section.nanson_density(F, normal)
        assert close(cut.deformed_area(u), exact)
    # Diagonal stretch (a, b, c): the plane z = 1/2 scales by a b.
    a, b, c = 1.1, 0.9, 1.3
    u = displacement(mesh, lambda x: np.array([(a - 1) * x[0], (b - 1) * x[1], (c - 1) * x[2]]))
    cut = section.CutSection(mesh, [0.5, 0.5, 0.5], [0, 0, 1])
    assert close(cut.deformed_area(u), a * b)


def test_deformed_area_quadratic_shear():
    # u = (x², 0, 0): on z = 1/2, cof(F) e_z = (1 + 2x) e_z, so the area is ∫(1 + 2x) = 2,
    # and P2 holds u exactly while degree 4 integrates the density exactly.
    mesh = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 2, 3, 4)
    u = displacement(mesh, lambda x: np.array([x[0] ** 2, 0 * x[0], 0 * x[0]]))
    assert close(section.CutSection(mesh, [0.5, 0.5, 0.5], [0, 0, 1]).deformed_area(u), 2.0)


# --- parallel against serial -----------------------------------------------------------------


def nonlinear(x):
    return np.array([0.1 * x[0] * x[1], 0.05 * x[1] * x[2] ** 2, 0.1 * np.sin(x[0] + x[2])])


@pytest.mark.mpi
def test_parallel_equals_serial():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    values = {}
    for name, c in (("self", MPI.COMM_SELF), ("world", comm)):
        mesh = dolfinx.mesh.create_box(c, [[0, 0, 0], [1, 1, 3]], [3, 3, 7])
        origin, normal = section.principal_plane(section.global_vertices(mesh, c))
        cut = section.CutSection(mesh, origin, normal)
        u = displacement(mesh, nonlinear)
        values[name] = (origin, normal, cut.area0(c), cut.deformed_area(u))
    (o1, n1, a1, d1), (o2, n2, a2, d2) = values["self"], values["world"]
    assert np.array_equal(o1, o2) and np.array_equal(n1, n2)  # the plane is bitwise the same
    assert close(a1, 1.0) and close(a2, a1)
    assert abs(d1 - 1.0) > 1e-3 and close(d2, d1)
    # Both ranks did part of the work: the section is split.
    mesh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [1, 1, 3]], [3, 3, 7])
    local = section.CutSection(mesh, o1, n1)._area0
    assert 0 < local < a1


@pytest.mark.mpi
def test_parallel_cylinder_equals_serial():
    comm = MPI.COMM_WORLD
    serial = cylinder_mesh(MPI.COMM_SELF)
    mesh = cylinder_mesh(comm)
    origin, normal = section.principal_plane(section.global_vertices(mesh))
    o1, n1 = section.principal_plane(section.global_vertices(serial))
    assert np.array_equal(origin, o1) and np.array_equal(normal, n1)
    areas = []
    for m in (serial, mesh):
        cut = section.CutSection(m, origin, normal)
        u = displacement(m, nonlinear)
        areas.append((cut.area0(), cut.deformed_area(u)))
    assert close(areas[1][0], areas[0][0]) and close(areas[1][1], areas[0][1])
