"""Statistics of the anatomical meshes: size, volume, reference cross-section, length.

One row per mesh (`statistics`, the columns of `COLUMNS`),

    geometry,muscle,subject,side,cells,vertices,volume_cm3,csa0_cm2,length_cm

which ``hyper meshstats`` (`hyper.commands.meshstats`) writes as a table with a figure
like the paper's Fig. 5B. Definitions (MODEL.md §4):

- volume: the integral of 1 over the mesh;
- csa0: the exact area of the cut of the mesh by the plane through the mean of all
  vertices, normal to their first principal axis (``section.principal_plane``,
  ``section.CutSection.area0``);
- length: the extent of the vertices along that axis (max - min of the projections);
- csa_solid, length_solid: the same by the solid's own frame (``section.solid_plane``):
  the plane through the centroid of the volume, normal to its principal axis of inertia.
  csa0 is what the growth model feeds back (MODEL.md §4), but the vertices' mean and axis
  move with where a mesher puts its vertices (fTetWild's meshes are denser near the
  surface: on the shipped meshes the vertex plane lies 3-39 mm off the centroid and tilts
  0.4-3.2° off the inertia axis), whereas the solid's frame is a property of the shape:
  the shipped meshes and `hyper mesh`'s agree with the STL's own frame to 0.5 mm and 0.15°.
  length_solid still depends on how the mesh rounds the two tips.

Every quantity counts each vertex and cell once, whatever the number of ranks. The
paper's group means of the volume (Devold et al. 2026, Discussion) are `PAPER_VOLUME_CM3`.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np

from hyper.fem import geometry as geo
from hyper.fem import section

COLUMNS = ("geometry", "muscle", "subject", "side", "cells", "vertices", "volume_cm3", "csa0_cm2", "length_cm",
           "csa_solid_cm2", "length_solid_cm")
# Group means of the initial volumes (cm³) as the paper reports them, to 0.1 cm³.
PAPER_VOLUME_CM3 = {"BFLH": 252.4, "ST": 190.1, "TA": 132.4}
PAPER_DECIMALS = 1


def statistics(geometry: geo.Geometry) -> dict:
    """One row of the table for a loaded geometry (in metres); collective."""
    mesh = geometry.mesh
    points = section.global_vertices(mesh)
    origin, normal = section.principal_plane(points)
    along = section.signed_distance(points, origin, normal)
    row = {"geometry": geometry.name}
    if geometry.name in geo.ANATOMICAL:
        row.update(zip(("muscle", "subject", "side"), geo.split_id(geometry.name)))
    row.update(
        cells=geometry.num_cells(),
        vertices=len(points),
        volume_cm3=geometry.reference_volume() * 1e6,
        csa0_cm2=section.CutSection(mesh, origin, normal).area0() * 1e4,
        length_cm=float(along.max() - along.min()) * 1e2,
    )
    origin, normal = section.solid_plane(mesh)
    along = section.signed_distance(points, origin, normal)
    row.update(csa_solid_cm2=section.CutSection(mesh, origin, normal).area0() * 1e4,
               length_solid_cm=float(along.max() - along.min()) * 1e2)
    return row


def group_means(rows, column: str = "volume_cm3") -> dict[str, float]:
    """Mean of ``column`` per muscle, in the order of geometry.MUSCLES."""
    means = {}
    for muscle in geo.MUSCLES:
        values = [row[column] for row in rows if row.get("muscle") == muscle]
        if values:
            means[muscle] = float(np.mean(values))
    return means


def matching_digits(value: float, reference: float) -> int:
    """How many significant digits of ``reference`` ``value`` reproduces when rounded
    to as many digits (0 if not even the first)."""
    digits = 0
    for n in range(1, 16):
        scale = 10.0 ** (np.floor(np.log10(abs(reference))) - n + 1)
        if round(value / scale) * scale != round(reference / scale) * scale:
            break
        digits = n
    return digits

