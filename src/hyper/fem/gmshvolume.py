"""gmsh's tetrahedra inside a closed surface, in a process of its own within a wall-time
budget (`tetrahedra`; `hyper.fem.meshing` chooses the sizes).

Why a process: gmsh can loop for ever in native code on a surface it cannot parametrize
(a tetrahedron's four triangles: classifySurfaces split "face 1" 10⁷ levels deep for over
ten minutes, with SIGTERM blocked), and native code cannot be interrupted from Python, so
the job would hang. The child (``python -m hyper.fem.gmshvolume IN.npz OUT.npz PARENT``) imports
numpy and gmsh only (never MPI: it must not join the parent's MPI job); it is killed when
its budget is spent, and ends itself when its parent is gone (a TERMed job).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from hyper.core import term
from hyper.core.params import InputError

PARENT_CHECK_S = 0.5  # how often the child looks whether its parent is still there


class OverBudget(RuntimeError):
    """gmsh had not finished when its time was up; the child is killed."""


def tetrahedra(points: np.ndarray, triangles: np.ndarray, *, size: float, tip_size: float, tips: np.ndarray,
               reach: float, feature_deg: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(x (n, 3), tetrahedra (m, 4)) of the surface at ``size``, falling to ``tip_size`` at
    ``tips`` and back to ``size`` within ``reach`` of them; InputError when gmsh fails,
    `OverBudget` when it has not finished after ``seconds``."""
    with tempfile.TemporaryDirectory(prefix="hyper-gmsh-") as folder:
        given, made = Path(folder) / "in.npz", Path(folder) / "out.npz"
        np.savez(given, points=points, triangles=triangles, size=size, tip_size=tip_size, tips=tips, reach=reach,
                 feature_deg=feature_deg)
        try:
            with term.spawning():
                done = subprocess.run([sys.executable, "-m", "hyper.fem.gmshvolume", str(given), str(made),
                                       str(os.getpid())],
                                      capture_output=True, text=True, timeout=seconds, env=child_environment())
        except subprocess.TimeoutExpired:  # subprocess.run has killed it
            raise OverBudget(f"gmsh still running after {seconds:g} s") from None
        if done.returncode != 0 or not made.is_file():
            last = (done.stderr.strip().splitlines() or ["no message"])[-1]
            raise InputError(f"gmsh could not mesh the surface: it ended with exit status {done.returncode} "
                             f"({last})")
        with np.load(made) as result:
            if "error" in result:
                raise InputError(f"gmsh could not mesh the surface: {result['error']}")
            return result["x"], result["tets"]


def child_environment() -> dict[str, str]:
    """The parent's environment without the process-manager variables of its MPI rank, so
    that nothing in the child could take itself for that rank (PMI_*, PMIX_*, MPI_*)."""
    return {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "PMIX_", "MPI_", "OMPI_"))}


def mesh(points, triangles, size, tip_size, tips, reach, feature_deg) -> tuple[np.ndarray, np.ndarray]:
    """The child's work: gmsh's Delaunay tetrahedra and Netgen's optimizer (meshing's docstring, step 3)."""
    import gmsh

    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("surface")
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).ravel())
        gmsh.model.mesh.classifySurfaces(math.radians(feature_deg), True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        loop = gmsh.model.geo.addSurfaceLoop([tag for _, tag in gmsh.model.getEntities(2)])
        gmsh.model.geo.addVolume([loop])
        points_at = [gmsh.model.geo.addPoint(*tip) for tip in tips]
        gmsh.model.geo.synchronize()
        field = gmsh.model.mesh.field
        distance = field.add("Distance")
        field.setNumbers(distance, "PointsList", points_at)
        ramp = field.add("Threshold")
        field.setNumber(ramp, "InField", distance)
        field.setNumber(ramp, "SizeMin", tip_size)
        field.setNumber(ramp, "SizeMax", size)
        field.setNumber(ramp, "DistMin", 0.0)
        field.setNumber(ramp, "DistMax", reach)
        field.setAsBackgroundMesh(ramp)
        # the field alone sets the size: not the STL's own points, nor the surface's spacing
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeMin", tip_size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.optimize("Netgen")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    finally:
        gmsh.finalize()
    position = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    position[node_tags] = np.arange(len(node_tags))
    tets = position[np.asarray(tet_nodes, dtype=np.int64).reshape(-1, 4)]
    used, compact = np.unique(tets, return_inverse=True)
    return coords.reshape(-1, 3)[used], compact.reshape(-1, 4)


def end_with_parent(parent: int) -> None:
    """A thread of the child: end it when its parent is gone (killed, or TERMed at once);
    gmsh's native calls let Python's threads run."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_S)
    os._exit(1)


def child(given: Path, made: Path, parent: int) -> int:
    threading.Thread(target=end_with_parent, args=(parent,), daemon=True).start()
    with np.load(given) as data:
        args = {k: data[k] for k in data}
    try:
        x, tets = mesh(args["points"], args["triangles"], float(args["size"]), float(args["tip_size"]), args["tips"],
                       float(args["reach"]), float(args["feature_deg"]))
    except Exception as err:  # gmsh raises a bare Exception with its last error
        np.savez(made, error=str(err))
        return 0
    np.savez(made, x=x, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(child(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])))
