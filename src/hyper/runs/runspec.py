"""What one coupled run is (`RunSpec`: geometry, protocol, parameters, settings; its
SHA-256 `digest` names the result) and where it writes (`Outputs`)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.core import io
from hyper.core.collective import on_rank0
from hyper.core.params import InputError, as_attributes, as_seed
from hyper.fem import fiberread as fr
from hyper.model import signaling
from hyper.model.material import MaterialParams
from hyper.model.protocols import Protocol
from hyper.runs import checkpoint as ckpt
from hyper.runs import fidelity

LINEAR_SOLVERS = ("lu", "iterative", "pmg", "auto")
# the fibre kinds of a mesh file (--fibers, hyper.runs.presets.MESH_FIBERS) that are its
# Stokes fibres: the file beside it, else computed
MESH_FIBERS_STOKES = ("auto", "stokes")
# uniform refinements a run takes (--refine, [numerics] refine): each multiplies the cells
# by 8, and 3 puts the idealized shape past what one LU factorisation holds on a workstation
# (fidelity, which counts refinements for --accuracy, holds the number)
MAX_REFINE = fidelity.MAX_REFINE
MESH_UNITS = {"m": 1.0, "mm": 1.0e-3}

# A muscle's longest side: the paper's are 0.1-0.45 m. Outside this, the declared unit
# is wrong (a file in millimetres read as metres is ~1000x too long).
MUSCLE_LENGTH_M = (0.01, 1.0)


def mesh_files(path: Path) -> list[Path]:
    """A mesh file and, for XDMF, its HDF5 data: what a mesh's SHA-256 hashes."""
    data = path.with_suffix(".h5")
    return [path] + ([data] if path.suffix == ".xdmf" and data.is_file() else [])


@dataclasses.dataclass(frozen=True)
class MeshFile:
    """A user's tetrahedral XDMF mesh with facet tags ``tags``: 1 and 2 the ends, 3 the
    lateral surface (the anatomical meshes' convention); lengths in ``unit``."""

    path: Path
    unit: str = "m"
    tags: str = "ft_small"

    def __post_init__(self):
        if self.unit not in MESH_UNITS:
            raise InputError(f"--mesh-unit: expected one of {', '.join(MESH_UNITS)}, got {self.unit!r}")
        if Path(self.path).suffix != ".xdmf":
            raise InputError(f"{self.path}: expected an XDMF mesh file (.xdmf with its .h5), "
                             f"got {Path(self.path).suffix!r}")

    def load(self, comm):
        from hyper.fem import geometry as geo

        geometry = geo.load_file(self.path, comm, name=self.path.stem, tags=self.tags, ends=(1, 2), lateral=3,
                                 scale=MESH_UNITS[self.unit])
        x = geometry.mesh.geometry.x
        lo, hi = np.empty(3), np.empty(3)
        comm.Allreduce(x.min(axis=0) if len(x) else np.full(3, np.inf), lo, op=MPI.MIN)
        comm.Allreduce(x.max(axis=0) if len(x) else np.full(3, -np.inf), hi, op=MPI.MAX)
        length = float(np.max(hi - lo))
        low, high = MUSCLE_LENGTH_M
        if not low <= length <= high:
            in_file = length / MESH_UNITS[self.unit]
            raise InputError(
                f"{self.path}: the mesh is {in_file:g} {self.unit} long (longest side of its bounding box), "
                f"i.e. {length:g} m, outside the {low:g}-{high:g} m of a muscle: its length unit is not "
                f"{self.unit!r}; declare the file's unit with --mesh-unit ({' or '.join(MESH_UNITS)})"
            )
        return geometry

    def shipped(self) -> str | None:
        """The built-in geometry whose mesh file this is, if it is one."""
        from hyper.fem import geometry as geo

        here = Path(self.path).resolve()
        return next((name for name, file in geo.GEOMETRIES.items()
                     if (Path(geo.MESHES_DIR) / file).resolve() == here), None)

    def identity(self) -> dict:
        return {"mesh_sha256": ckpt.file_digest(*mesh_files(self.path)), "unit": self.unit, "tags": self.tags}

    @property
    def fibres(self) -> Path:
        """Where this mesh's Stokes fibres are, if it has them: beside it, as `hyper mesh` writes them."""
        from hyper.fem import fibers

        return Path(self.path).parent / fibers.FILE_NAME

    def fibre_file(self, asked: str = "auto") -> Path:
        """The fibre file a run with --fibers ``asked`` reads beside this mesh: its own
        (`fibres`), or for stokes its Stokes fibres, ``fibers_stokes.h5`` where its own are of
        another kind (a Laplace mesh of `hyper mesh`, a shipped one) or that file exists."""
        from hyper.fem import fibers

        return fibers.stokes_path(self.fibres.parent) if asked == "stokes" else self.fibres

    def fibre_kind(self) -> str:
        """The kind of fibres the file beside this mesh holds ("stokes" where there is none)."""
        return fr.stored_fibres(self.fibres)[0] if self.fibres.is_file() else "stokes"

    def fibre_cache(self, asked: str = "auto") -> tuple[Path | None, str]:
        """(where Stokes fibres computed for this mesh are kept, or None; why not there).

        Beside the mesh, where `hyper mesh` puts them and every later run (any job, any
        output folder) finds them; never in a shipped mesh folder (the package's data,
        which only `hyper fibers` and `hyper mesh` write) or a folder this process cannot
        write: there every run computes them again (a few seconds on a mesh of 10k cells).
        """
        from hyper.fem import geometry as geo

        folder = Path(self.path).resolve().parent
        if folder.is_relative_to(Path(geo.MESHES_DIR).resolve()):
            return None, "a shipped mesh folder, which runs never write"
        if not os.access(folder, os.W_OK):
            return None, "its folder is not writable"
        return self.fibre_file(asked), ""


def check_geometry(comm, name: str, option: str = "--geometry") -> None:
    """A built-in geometry that can run: known, its mesh file there, and (anatomical
    meshes) its fibre field computed. Collective (rank 0 looks at the files)."""
    from hyper.fem import fibers
    from hyper.fem import geometry as geo

    if name not in geo.GEOMETRIES:
        raise InputError(f"{option}: unknown geometry {name!r}; known: {', '.join(geo.GEOMETRIES)}")
    path = geo.MESHES_DIR / geo.GEOMETRIES[name]
    if not on_rank0(comm, path.is_file):
        raise InputError(f"{option} {name}: {path}: no such mesh file")
    fibres = fibers.fiber_path(name) if name in geo.ANATOMICAL + geo.MESHED else None
    if fibres is not None and not on_rank0(comm, lambda: io.is_complete(fibres)):
        raise InputError(f"{option} {name}: {fibres}: no complete fibre file; compute it with "
                         f"`hyper fibers --geometries {name}`")


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """Everything that defines one run's result, and how it is solved."""

    geometry: str  # a built-in geometry id, or the stem of ``mesh``
    protocol: Protocol
    params: signaling.SignalingParams = signaling.SignalingParams()
    settings: object = None  # GrowthSettings; None: the defaults
    petsc_options: Mapping = dataclasses.field(default_factory=dict)
    mesh: MeshFile | None = None
    # per-cell signaling parameters: p0 (1 + ε ξ) drawn from this model with this seed
    heterogeneity: object = None  # hyper.model.heterogeneity.Heterogeneity
    seed: int | None = None
    # how the Newton steps are solved: "lu", "iterative", "pmg" or "auto" (by memory); all give
    # the answer to the Newton tolerance, so the choice is not part of the digest
    linear_solver: str = "lu"
    # the fidelity choice (--accuracy) that set the steps; "auto" completes it with the solver
    choice: fidelity.Choice | None = None
    # the discretisation: uniform refinements of the mesh, and the quadrature degree
    # (None: the geometry's own, 4)
    refine: int = 0
    quadrature_degree: int | None = None
    # the original code's idealized shape (MODEL.md §9): its end tags ("tags") and its
    # fibres ("original": P2 used as they are, surface integrals at UFL's estimated degree)
    ends: str = "disks"
    fibers: str = "auto"
    material: MaterialParams = MaterialParams()  # the muscle law's parameters (--material)
    # fibres from data (--fibers FILE, hyper.fem.fiberdata), with fibers = "data"
    fiber_data: fr.Source | None = None

    def __post_init__(self):
        if self.settings is None:
            from hyper.fem.coupled import GrowthSettings

            object.__setattr__(self, "settings", GrowthSettings())
        if self.linear_solver not in LINEAR_SOLVERS:
            raise InputError(f"--linear-solver: expected one of {', '.join(LINEAR_SOLVERS)}, "
                             f"got {self.linear_solver!r}")
        if (self.heterogeneity is None) != (self.seed is None):
            raise InputError("per-cell parameters need both a heterogeneity model and a seed")
        if self.seed is not None:
            as_seed(self.seed, "seed")  # every job's seed, however given: it is stored as an attribute
        if isinstance(self.refine, bool) or not isinstance(self.refine, int) or not 0 <= self.refine <= MAX_REFINE:
            raise InputError(f"expected an integer in [0, {MAX_REFINE}], got {self.refine!r}", field="refine")
        if (self.fibers == "data") != (self.fiber_data is not None):
            raise InputError("fibres from data (fibers = 'data') need their file, and a file makes them so")
        if self.quadrature_degree is not None and not (isinstance(self.quadrature_degree, int)
                                                       and 1 <= self.quadrature_degree <= 12):
            raise InputError(f"expected an integer in [1, 12], got {self.quadrature_degree!r}",
                             field="quadrature_degree")

    @property
    def label(self) -> str:
        return f"{self.geometry}/{self.protocol.name}"

    def describe(self) -> dict:
        """What the digest hashes: geometry, protocol, parameters, settings, solver options."""
        described = {k: ("per cell" if isinstance(v, np.ndarray) else v) for k, v in as_attributes(self.params).items()}
        # the files' bytes, not only the name: a mesh remade in place (`hyper mesh --force`,
        # `make new-meshes`) is another run, not one whose result is already there
        geometry = ({"name": self.geometry, "sha256": ckpt.file_digest(*self.input_files())}
                    if self.mesh is None else {**self.mesh.identity(), "fibers": self.mesh_fibres()})
        out = {
            "geometry": geometry,
            "protocol": self.protocol.to_attributes(),
            "params": described,
            "settings": self.settings.model_attributes(),
            "petsc_options": dict(self.petsc_options),
        }
        if self.heterogeneity is not None:
            out["heterogeneity"] = {**self.heterogeneity.attributes(), "seed": self.seed}
        # only where they differ from the defaults, so that the digests of default runs stay
        if self.refine:
            out["refine"] = self.refine
        if self.quadrature_degree is not None:
            out["quadrature_degree"] = self.quadrature_degree
        if self.ends != "disks":
            out["ends"] = self.ends
        if self.fibers != "auto":
            out["fibers"] = self.fibers
        if self.fiber_data is not None:  # the file's bytes and how it is read, not its name
            files = [self.fiber_data.path] + ([self.fiber_data.fa] if self.fiber_data.fa is not None else [])
            out["fiber_data"] = {**{k: v for k, v in self.fiber_data.attributes().items() if k not in ("file", "fa")},
                                 "sha256": ckpt.file_digest(*files)}
        if self.material != MaterialParams():
            out["material"] = as_attributes(self.material)
        return out

    def digest(self) -> str:
        return ckpt.digest(self.describe())

    def mesh_fibres(self) -> str:
        """A mesh file's Stokes fibres, as the digest names them: the SHA-256 of the fibre
        file beside it, or "computed" (each run computes them); "" for another kind."""
        if self.fibers not in MESH_FIBERS_STOKES:
            return ""
        path = self.mesh.fibre_file(self.fibers)
        return ckpt.file_digest(path) if io.is_complete(path) else "computed"

    def mesh_files(self) -> list[Path]:
        """The files of this run's mesh (`mesh_files`)."""
        if self.mesh is not None:
            return mesh_files(Path(self.mesh.path))
        from hyper.fem import geometry as geo

        return mesh_files(geo.MESHES_DIR / geo.GEOMETRIES[self.geometry])

    def input_files(self) -> list[Path]:
        """The files a built-in geometry's run reads: its mesh and, beside it, the fibre file of
        the fibres it runs (its own, or with --fibers stokes or original its Stokes fibres)."""
        from hyper.fem import fibers

        files = self.mesh_files()
        kind = "stokes" if self.fibers in ("stokes", "original") else "auto"
        stored = fibers.fiber_path(self.geometry, kind=kind) if self.mesh is None else None
        return files + ([stored] if stored is not None and stored.is_file() else [])

    @property
    def unit_fibres(self) -> bool:
        """Whether the mechanics normalises the fibres at its points (all but the original's)."""
        from hyper.fem import fibers

        return self.fibers not in fibers.UNNORMALISED_KINDS



@dataclasses.dataclass(frozen=True)
class Outputs:
    """The files of one run, named after its result ``h5``."""

    h5: Path

    @property
    def checkpoint(self) -> Path:
        return self.h5.with_name(self.h5.stem + ".ckpt.h5")

    @property
    def status(self) -> Path:
        return self.h5.with_name(self.h5.stem + ".status.json")

    @property
    def fields(self) -> Path:
        return self.h5.with_name(self.h5.stem + "_fields.xdmf")

    @property
    def snapshots(self) -> list[Path]:
        """The snapshot files: the fields' XDMF and the HDF5 file of its data."""
        return [self.fields, self.fields.with_suffix(".h5")]

    def is_current(self, digest: str) -> bool:
        """A complete result of the run with this digest exists."""
        if not io.is_complete(self.h5):
            return False
        with io.reading_h5(self.h5) as f:
            return f.attrs.get("run_digest") == digest

    def store(self, series: dict, attrs: Mapping, groups: Mapping) -> None:
        """Write the result, then drop the checkpoint and status it no longer needs (one rank)."""
        io.write_series(self.h5, series, attrs=attrs, groups=groups)
        self.checkpoint.unlink(missing_ok=True)
        self.status.unlink(missing_ok=True)


def result_groups(spec: RunSpec, choice: fidelity.Choice | None = None) -> dict:
    """The attribute groups every run's result carries; ``choice`` the run's fidelity
    choice (`Result.choice`); ``spatial`` the estimated spatial error of its growth."""
    groups = {"signaling": as_attributes(spec.params), "material": as_attributes(spec.material),
              "protocol": spec.protocol.to_attributes(), "settings": dataclasses.asdict(spec.settings)}
    if spec.heterogeneity is not None:
        groups["heterogeneity"] = {**spec.heterogeneity.attributes(), "seed": spec.seed}
    if choice is not None:
        groups["fidelity"] = choice.as_attributes()
    groups["spatial"] = spatial_error(spec).as_attributes()
    return groups


def table_name(geometry: str, mesh: MeshFile | None, fibers: str = "auto") -> tuple[str, bool, str]:
    """The name `fidelity`'s tables know a run's mesh by, whether that is a user's mesh
    file, and the kind of its fibres: a shipped mesh given as a file (with the fibres beside
    it, the same run as its --geometry) is its geometry; a mesh file's fibres, and a built-in
    geometry's own, are what the file beside it holds (Stokes where there is none: a run
    computes them; the shipped meshes' are Laplace), --fibers laplace makes Laplace fibres on
    any, and --fibers stokes or original takes an anatomical mesh's Stokes fibres."""
    from hyper.fem import geometry as geo

    shipped = mesh.shipped() if mesh is not None else None
    name = shipped or geometry
    if fibers == "laplace":
        kind = "laplace"
    elif mesh is not None and not shipped:
        kind = mesh.fibre_kind()
    elif fibers == "auto" and name in geo.ANATOMICAL + geo.MESHED:  # what its fibre file holds
        kind = MeshFile(geo.MESHES_DIR / geo.GEOMETRIES[name], "mm").fibre_kind()
    else:
        kind = "stokes"
    return (shipped, False, kind) if shipped else (geometry, mesh is not None, kind)


def spatial_error(spec: RunSpec) -> fidelity.Spatial:
    """The estimated spatial error of the growth of ``spec`` (`fidelity.spatial`)."""
    name, mesh_file, fibres = table_name(spec.geometry, spec.mesh, spec.fibers)
    return fidelity.spatial(name, spec.refine, mesh_file=mesh_file, fibres=fibres)
