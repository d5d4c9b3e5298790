"""Named presets of settings (``--settings``): every switch of the original code at once.

A preset maps setting fields to values. `settings` builds a settings dataclass from its
defaults, then the preset's values for the fields that dataclass has, then the values
the user chose explicitly (an option left out is None, not chosen), so an explicit option
always wins over the preset and one preset serves every job's dataclass (GrowthSettings
now; the contraction's settings take the fields they have). A dataclass with a
``preset`` field records the name.

"original" is the paper's code as MODEL.md §9 reads it; each switch is also an option
of its own, default off.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Mapping
from pathlib import Path

from hyper.core.params import InputError, build
from hyper.fem import fiberread as fr
from hyper.model.signaling.integrators import METHODS

PRESETS: dict[str, dict] = {
    "default": {},
    "original": {
        "growth_dt": 1.0,  # h
        "signaling_method": "rk45-original",
        "growth_increment": "left-point",
        "grow_during_sessions": False,
        "consistent_stress": False,
        "csa_method": "box",
        "growth_fields": "dg1",
        # RunSpec fields (see `shape`): the idealized shape's XDMF end tags; the original's
        # fibres (the idealized shape's P2 field, the anatomical meshes' Stokes fibres)
        "ends": "tags",
        "fibers": "original",
    },
}
NAMES = tuple(PRESETS)

# the options that set each switch, for errors that name what the user typed
OPTIONS = {"signaling_method": "--signaling-method", "growth_increment": "--growth-increment",
           "grow_during_sessions": "--skip-sessions", "consistent_stress": "--fe-stress",
           "csa_method": "--csa-method", "growth_fields": "--growth-fields", "sections": "--sections",
           "detraining": "--detraining", "fiber_growth": "--fiber-growth",
           "stimulus": "--stimulus"}
SHAPE_DEFAULTS = {"ends": "disks", "fibers": "auto"}  # what every geometry but the idealized one runs
# --fibers: auto and original for the built-in geometries, stokes for the anatomical ones,
# axial and principal too for a mesh file, and laplace for any geometry
LAPLACE = "laplace"
MESH_FIBERS = ("auto", "stokes", "axial", "principal", LAPLACE)
FIBER_CHOICES = ("auto", "original", *MESH_FIBERS[1:])
DATA = "data"  # the kind of the fibres of a data file (--fibers FILE, hyper.fem.fiberdata)
# where --fibers FILE stands for one file per geometry (hyper cohort)
GEOMETRY_FIELD = "{geometry}"
DATA_HELP = ("or a fibre data FILE (hyper.fem.fiberdata, docs/fibres-from-data.md): a DTI image (.nii, .nii.gz: "
             "eigenvector or tensor), streamlines (.vtk, .vtp, .npz), a point cloud (.csv, .npz: x,y,z,ax,ay,az) "
             "or a fibre file (.h5), in the mesh's world frame, sampled at the loaded mesh's nodes")
PER_GEOMETRY_HELP = f" ({GEOMETRY_FIELD} in FILE stands for each geometry's id: one file per geometry)"


def settings(cls, name: str, chosen: Mapping, options: Mapping[str, str] | None = None):
    """``cls`` from its defaults, preset ``name`` and the ``chosen`` values that are not None.

    ``options`` maps fields to the options that set them, for `hyper.core.params.build`'s errors.
    """
    if name not in PRESETS:
        raise InputError(f"--settings: expected one of {', '.join(NAMES)}, got {name!r}")
    fields = {f.name for f in dataclasses.fields(cls)}
    values = {k: v for k, v in PRESETS[name].items() if k in fields}
    values.update({k: v for k, v in chosen.items() if v is not None})
    if "preset" in fields:
        values["preset"] = name
    return build(cls, {**OPTIONS, **(options or {})}, **values)


METHOD_HELP = ("rk4: classical RK4 with steps landing on every switch (converged at 0.05 h); rk45-original: "
               "the original code's SciPy RK45 at rtol 1e-3, atol 1e-6, steps of at most --signaling-dt, "
               "restarted only at session starts and ends, from its N0 = 1.000768 (MODEL.md §9)")


def method_option(p: argparse.ArgumentParser, default: str | None = "rk4") -> None:
    """--signaling-method, the same for every job that integrates the signaling ODEs
    (default None where a preset may choose it: rk4 unless it does)."""
    p.add_argument("--signaling-method", choices=METHODS, default=default,
                   help=METHOD_HELP + ("" if default else "; rk4 unless --settings sets it"))


def add_options(p: argparse.ArgumentParser, *, signaling_method: bool = True, several: bool = False) -> None:
    """--settings and the switches of a growth run; ``signaling_method`` False where the
    parser has its --signaling-method already; ``several``: the job runs several geometries."""
    from hyper.fem.coupled import CSA_METHODS
    from hyper.fem.geometry import IDEALIZED_ENDS
    from hyper.fem.growthfield import GROWTH_FIELDS
    from hyper.model.growth import INCREMENTS

    p.add_argument("--settings", choices=NAMES, default="default",
                   help="a named preset: original turns on every switch of the original code at once "
                        "(--signaling-method rk45-original, --growth-increment left-point, --skip-sessions, "
                        "--fe-stress, --csa-method box, --growth-fields dg1, --growth-dt 1, --fibers original: the "
                        "anatomical meshes' Stokes fibres, and on the idealized shape --ends tags); an explicit "
                        "option wins over it")
    if signaling_method:
        method_option(p, default=None)
    p.add_argument("--growth-increment", choices=INCREMENTS,
                   help="dN of a growth step: exact (N's change over it) or left-point (f at its start × Δtg, "
                        "the original code); exact unless --settings sets it")
    p.add_argument("--skip-sessions", action=argparse.BooleanOptionalAction,
                   help="no growth during sessions (the original code); off unless --settings sets it")
    p.add_argument("--fe-stress", action=argparse.BooleanOptionalAction,
                   help="P = Fe S (the original code) instead of the consistent det(Fg) Fe S Fg⁻ᵀ; "
                        "off unless --settings sets it")
    p.add_argument("--csa-method", choices=CSA_METHODS,
                   help="the CSA the feedback sees on a mesh without a tagged mid-section: the exact cut by the "
                        "vertices' plane (MODEL.md §4), the original code's box staircase (MODEL.md §9), or the "
                        "exact cut by the solid's plane of inertia (the same on any mesh of the shape); all are "
                        "recorded (csa_ratio_cut, csa_ratio_box, csa_ratio_solid); cut unless --settings sets it")
    p.add_argument("--growth-fields", choices=GROWTH_FIELDS,
                   help="where G, Ḡ and A live: at the quadrature points, or at the nodes of DG1 fields "
                        "(the original code); quadrature unless --settings sets it")
    p.add_argument("--ends", choices=IDEALIZED_ENDS,
                   help="the idealized shape's spring ends: the flat end disks, or the XDMF's end tags with "
                        "their lateral band (the original code); disks unless --settings sets it")
    p.add_argument("--fibers", metavar="KIND|FILE",
                   help="the geometry's fibres (auto: the anatomical meshes' Laplace fibres, the potential flow "
                        "between the ends that the shipped fibre files hold, converged where the Stokes fibres are "
                        "not), laplace (made on the mesh run where no file holds them: hyper.fem.laplace), stokes "
                        "(an anatomical mesh's Stokes fibres, the paper's), original (the original code's: on the "
                        "idealized shape its P2 field used as it is, surface integrals at UFL's estimated degree; on "
                        "an anatomical mesh its Stokes fibres); a --mesh file's: auto (the fibre file beside it, "
                        "else Stokes fibres computed), stokes, laplace, axial (e_z) or principal (its principal "
                        f"axis); {DATA_HELP}{PER_GEOMETRY_HELP if several else ''}; auto unless --settings sets it")


def shape(args: argparse.Namespace, geometries, mesh: bool = False) -> dict:
    """The RunSpec fields ends and fibers: explicit options, else the preset's on the
    idealized shape (the only one the original's end tags and fibres exist for); a mesh
    file (``mesh``) takes the fibres of `runspec.MESH_FIBERS`."""
    if is_data(args.fibers, FIBER_CHOICES):
        if args.ends not in (None, SHAPE_DEFAULTS["ends"]):
            raise InputError("--ends applies to the idealized shape with its own fibres, not with --fibers FILE")
        return {**SHAPE_DEFAULTS, "fibers": DATA}
    explicit = {"ends": args.ends, "fibers": args.fibers}
    if mesh:
        if args.ends not in (None, SHAPE_DEFAULTS["ends"]):
            raise InputError("--ends applies to the idealized shape only, not to a --mesh file")
        if args.fibers not in (None, *MESH_FIBERS):
            raise InputError(f"--fibers {args.fibers}: a --mesh file's fibres are one of {', '.join(MESH_FIBERS)}")
        return {**SHAPE_DEFAULTS, **({"fibers": args.fibers} if args.fibers is not None else {})}
    if args.fibers == LAPLACE:
        if args.ends not in (None, SHAPE_DEFAULTS["ends"]):
            raise InputError("--ends applies to the idealized shape with its own fibres, not with --fibers laplace")
        return {**SHAPE_DEFAULTS, "fibers": LAPLACE}
    own_fibres = [g for g in geometries if g in ("idealized", "cylinder")]
    if args.fibers in ("axial", "principal") or (args.fibers == "stokes" and own_fibres):
        where = "a --mesh file and the anatomical meshes" if args.fibers == "stokes" else "a --mesh file"
        raise InputError(f"--fibers {args.fibers} applies to {where}; the idealized shape and the cylinder "
                         "have their own fibres (auto), and the idealized shape the original's (original)")
    if args.ends not in (None, SHAPE_DEFAULTS["ends"]) and set(geometries) != {"idealized"}:
        raise InputError("--ends applies to the idealized shape only")
    if args.fibers == "original" and "cylinder" in geometries:
        raise InputError("--fibers original: the original code's fibres are the idealized shape's and the anatomical "
                         "meshes' (their Stokes fibres), not the cylinder's")
    out = dict(SHAPE_DEFAULTS)
    preset = PRESETS[args.settings]
    if set(geometries) == {"idealized"}:
        out.update({k: v for k, v in preset.items() if k in out})
    elif "cylinder" not in geometries and "fibers" in preset:  # on an anatomical mesh, its Stokes fibres
        out["fibers"] = preset["fibers"]
    out.update({k: v for k, v in explicit.items() if v is not None})
    return out


def is_data(value: str | None, kinds) -> bool:
    """Whether a --fibers value names a data file rather than one of ``kinds`` (InputError
    if it is neither)."""
    if value is None or value in kinds:
        return False
    if fr.suffix(Path(value)) not in fr.FORMATS:
        kinds = f"one of {', '.join(kinds)} or " if kinds else ""
        raise InputError(f"--fibers {value}: expected {kinds}a fibre data file ({', '.join(fr.FORMATS)})")
    return True


def data_source(args: argparse.Namespace, kinds=FIBER_CHOICES, geometry: str | None = None) -> fr.Source | None:
    """The fibre data file of --fibers FILE and its options (None for a kind), for
    ``geometry`` where FILE holds `GEOMETRY_FIELD`. Its options without a file are an error."""
    options = {"--fibers-unit": args.fibers_unit != "auto", "--fibers-min-fa": args.fibers_min_fa != fr.MIN_FA,
               "--fibers-radius": args.fibers_radius is not None, "--fibers-fa": args.fibers_fa is not None}
    if not is_data(args.fibers, kinds):
        given = [name for name, set_ in options.items() if set_]
        if given:
            raise InputError(f"{given[0]} applies to --fibers FILE (fibres from data); --fibers is "
                             f"{args.fibers or 'auto'}")
        return None
    text = args.fibers if geometry is None else args.fibers.replace(GEOMETRY_FIELD, geometry)
    try:
        radius = None if args.fibers_radius is None else args.fibers_radius * 1e-3  # mm on the command line
        return fr.Source(Path(text), args.fibers_unit, args.fibers_min_fa, radius, args.fibers_fa)
    except InputError as err:
        raise InputError(f"--fibers {args.fibers}: {err}" if text == args.fibers else f"--fibers {args.fibers} "
                         f"for {geometry}: {err}") from None


def chosen(args: argparse.Namespace) -> dict:
    """The switches the command line set, by setting field (None: not given); --sections
    and --detraining are `hyper.commands.grow.model_options`."""
    return {
        "signaling_method": args.signaling_method,
        "growth_increment": args.growth_increment,
        "grow_during_sessions": None if args.skip_sessions is None else not args.skip_sessions,
        "consistent_stress": None if args.fe_stress is None else not args.fe_stress,
        "csa_method": args.csa_method,
        "growth_fields": args.growth_fields,
        "sections": args.sections,
        "detraining": args.detraining,
        "fiber_growth": args.fiber_growth,
        "stimulus": args.stimulus,
    }
