"""hyper mesh on degenerate but valid closed surfaces: refused with one `error:` line, or
meshed, within seconds (hyper.fem.meshing.check_meshable, then gmsh in a process of its own
stopped after its budget, hyper.fem.gmshvolume).

A tetrahedron (4 triangles) made gmsh's classifySurfaces loop for ever with SIGTERM
blocked; a 0.05 mm sheet and a 0.01 mm needle ran for minutes; a cube crashed after the
mesh (no long axis for the mid-section).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hyper.core.params import InputError
from hyper.fem import gmshvolume
from hyper.fem import meshing as hm

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def box(a: float, b: float, c: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed a x b x c box (mm), 12 outward triangles."""
    points = np.array([[x, y, z] for x in (0, a) for y in (0, b) for z in (0, c)], dtype=float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return points, np.array([t for q, r, s, u in quads for t in ((q, r, s), (q, s, u))])


def tetrahedron(side: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    points = np.array([[0, 0, 0], [side, 0, 0], [0, side, 0], [0, 0, side]], dtype=float)
    return points, np.array([(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)])


def prism() -> tuple[np.ndarray, np.ndarray]:
    """A triangular prism 60 mm long: the fewest triangles (8) with two ends and a side."""
    points = np.array([[0, 0, 0], [0, 20, 0], [0, 10, 17], [60, 0, 0], [60, 20, 0], [60, 10, 17]], dtype=float)
    return points, np.array([(0, 2, 1), (3, 4, 5), (0, 1, 4), (0, 4, 3), (1, 2, 5), (1, 5, 4), (2, 0, 3), (2, 3, 5)])


def write_stl(path: Path, points: np.ndarray, triangles: np.ndarray) -> Path:
    record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    data = np.zeros(len(triangles), dtype=record)
    data["corners"] = points[triangles]
    path.write_bytes(bytes(80) + np.uint32(len(triangles)).tobytes() + data.tobytes())
    return path


DEGENERATE = {
    "tetrahedron": (tetrahedron(), r"4 triangles; .* at least 8 triangles"),
    "sheet": (box(50, 50, 0.05), r"too thin for 8000 cells: .* 0\.0499 mm, 0\.096 of their size .*"
                                 r"give --cells 244461 or more"),
    "needle": (box(100, 0.01, 0.01), r"too thin for 8000 cells: .* 0\.22 of their size"),
    "foil": (box(100, 100, 0.001), r"too thin .* even --cells 2000000 is too few: a sheet or a needle"),
    "cube": (box(10, 10, 10), r"no long axis"),
    "square_plate": (box(50, 50, 5), r"no long axis"),
}


@pytest.mark.parametrize("case", DEGENERATE)
def test_a_degenerate_surface_is_refused_before_gmsh(case):
    (points, triangles), message = DEGENERATE[case]
    hm.check_surface(Path(case), points, triangles)  # valid closed surfaces, all of them
    with pytest.raises(InputError, match=message):
        hm.check_meshable(Path(case), points, triangles, hm.DEFAULT_CELLS)


def test_the_surface_covariance_is_the_exact_one_of_the_area():
    # a 60 x 20 x 20 box: faces' area moments; the diagonals that cut its faces do not count
    points, triangles = box(60, 20, 20)
    covariance = hm.surface_covariance(points, triangles)
    area = 2 * 400 + 4 * 1200
    xx = (2 * 400 * 30**2 + 4 * 1200 * 60**2 / 12) / area
    yy = (2 * 400 * 20**2 / 12 + 2 * 1200 * 10**2 + 2 * 1200 * 20**2 / 12) / area
    assert np.allclose(covariance, np.diag([xx, yy, yy]), atol=1e-9)


def test_the_bounds_let_the_least_surfaces_and_the_fewest_cells_through():
    for points, triangles in (prism(), box(60, 20, 20)):
        hm.check_meshable(Path("least"), points, triangles, hm.DEFAULT_CELLS)
    # the thickness bound follows --cells: the sheet is refused for 8000 cells, not for 300000
    hm.check_meshable(Path("sheet"), *box(50, 20, 0.05), 300_000)


def test_the_tetrahedron_is_refused_by_the_job_at_once(tmp_path):
    """The job itself, in a process of its own with a time limit (the hang it was)."""
    stl = write_stl(tmp_path / "tetrahedron.stl", *tetrahedron())
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "hyper.mesh", str(stl), "--output", str(tmp_path / "out")],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60)
    assert time.monotonic() - start < 20
    assert done.returncode == 2 and done.stdout == "", done.stderr
    assert done.stderr.startswith("error: ") and len(done.stderr.splitlines()) == 1, done.stderr
    assert not (tmp_path / "out").exists()


def test_the_least_surface_meshes_within_seconds():
    points, triangles = prism()
    start = time.monotonic()
    x, tets = hm.tetrahedralize(points, triangles, 1000, budget_s=60)
    assert time.monotonic() - start < 30 and 500 < len(tets) < 2000
    assert hm.signed_volumes(x, tets).min() != 0


def gmsh_children() -> list[int]:
    found = []
    for status in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if b"hyper.fem.gmshvolume" in status.read_bytes():
                found.append(int(status.parent.name))
        except OSError:
            continue
    return found


def test_gmsh_past_its_budget_is_killed_with_a_clear_refusal():
    """The mechanism on what made gmsh loop for ever: the tetrahedron, past the checks."""
    points, triangles = tetrahedron()
    before = set(gmsh_children())
    start = time.monotonic()
    with pytest.raises(InputError, match=r"gmsh had not meshed the surface after 2 s \(--gmsh-budget\) and was "
                                         r"stopped"):
        hm.gmsh_volume(points, triangles, 3.0, hm.extremes(points), 1.0, 5.0, time.monotonic() + 2.0, 2.0)
    assert time.monotonic() - start < 10
    assert set(gmsh_children()) <= before


def test_gmsh_ends_with_the_job_that_started_it(tmp_path):
    """A job TERMed while gmsh runs ends at once (hyper.core.term); its gmsh must not loop on."""
    code = ("import numpy as np, sys\nsys.path.insert(0, 'tests')\nfrom test_mesh_bounds import tetrahedron\n"
            "from hyper.fem import gmshvolume\npoints, triangles = tetrahedron()\n"
            "gmshvolume.tetrahedra(points, triangles, size=3.0, tip_size=1.0, tips=points[:2], reach=5.0, "
            "feature_deg=60.0, seconds=120)\n")
    before = set(gmsh_children())
    job = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=ENV)
    try:
        end = time.monotonic() + 30
        while not (mine := set(gmsh_children()) - before):
            assert job.poll() is None and time.monotonic() < end, "gmsh did not start"
            time.sleep(0.1)
        time.sleep(1.0)  # into classifySurfaces' loop
        job.send_signal(signal.SIGKILL)
        job.wait(timeout=10)
        end = time.monotonic() + 10
        while set(gmsh_children()) & mine:
            assert time.monotonic() < end, "gmsh still runs 10 s after its job ended"
            time.sleep(0.1)
    finally:
        job.kill()
        for pid in set(gmsh_children()) - before:
            os.kill(pid, signal.SIGKILL)


def test_the_child_never_joins_the_parents_mpi_job(monkeypatch):
    monkeypatch.setenv("PMI_RANK", "1")
    monkeypatch.setenv("PMIX_RANK", "1")
    assert not any(k.startswith(("PMI_", "PMIX_")) for k in gmshvolume.child_environment())
