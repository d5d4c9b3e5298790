"""The study file of one run, as TOML text: what every growth result records as ``study``.

`hyper study` on this text (saved to a file) reruns the result's run with the same
digest: the geometry (a built-in id, or the mesh file by its absolute path), the
protocol (a built-in name, or its sessions written out), every signaling and material
parameter, the per-cell heterogeneity and the numerics. A grow or cohort run records
the study it is equivalent to; PETSc options, which no study key sets, are a comment.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from hyper.core.params import as_attributes
from hyper.model import protocols


def value(v) -> str:
    """A TOML value: a string, boolean, number or an array of them."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "nan"
        return ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        # TOML's basic strings escape as JSON's do

        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {v!r}")


def table(header: str, values: dict) -> list[str]:
    return [f"[{header}]", *(f"{k} = {value(v)}" for k, v in values.items()), ""]


def protocol_lines(protocol) -> tuple[list[str], list[str]]:
    """(the ``protocols`` entries, the [[protocol]] lines) of a run's protocol: its name
    where it is the built-in protocol of that name, else its sessions."""
    if protocol.name in protocols.NAMES:
        mine, builtin = protocol.to_attributes(), protocols.named(protocol.name).to_attributes()
        if mine.keys() == builtin.keys() and all(np.array_equal(mine[k], builtin[k]) for k in mine):
            return [protocol.name], []
    lines = ["[[protocol]]", f"name = {value(protocol.name)}", f"end = {value(float(protocol.end))}", ""]
    for s in protocol.sessions:
        lines += ["[[protocol.session]]", f"start = {value(float(s.start))}",
                  f"duration = {value(float(s.duration))}", f"intensity = {value(float(s.intensity))}",
                  *([] if s.stretch is None else [f"stretch = {value(float(s.stretch))}"]), ""]
    return [], lines


def mesh_fibre_keys(source) -> dict:
    """A [[mesh]] table's keys of fibres from data (`hyper.analysis.study.MESH_FIBRE_KEYS`)."""
    out = {"fibers": str(source.path.resolve()), "fibers_unit": source.unit, "fibers_min_fa": source.min_fa}
    if source.radius is not None:
        out["fibers_radius_mm"] = source.radius * 1e3
    if source.fa is not None:
        out["fibers_fa"] = str(source.fa.resolve())
    return out


def study_text(spec) -> str:
    """The study file of the run ``spec`` (a `hyper.runs.driver.RunSpec`)."""
    names, protocol = protocol_lines(spec.protocol)
    lines = [f"# the study of the run {spec.label}: `hyper study FILE` reruns it", ""]
    lines.append(f"geometries = {value([spec.geometry] if spec.mesh is None else [])}")
    lines += [f"protocols = {value(names)}", ""]
    if spec.mesh is not None:
        lines += ["[[mesh]]", f"file = {value(str(spec.mesh.path.resolve()))}", f"unit = {value(spec.mesh.unit)}"]
        if spec.fiber_data is not None:
            lines += [f"{key} = {value(v)}" for key, v in mesh_fibre_keys(spec.fiber_data).items()]
        lines.append("")
    lines += protocol
    lines += table("signaling", as_attributes(spec.params))
    lines += table("material", as_attributes(spec.material))
    if spec.heterogeneity is not None:
        lines += table("heterogeneity", {**spec.heterogeneity.attributes(), "seed": spec.seed})
    settings = dataclasses.asdict(spec.settings)
    numerics = {"growth_dt": settings["growth_dt"], "signaling_dt": settings["signaling_dt"],
                "linear_solver": spec.linear_solver, "max_halvings": settings["max_halvings"],
                "feedback": settings["feedback"], "grow_during_sessions": settings["grow_during_sessions"],
                "consistent_stress": settings["consistent_stress"]}
    # beyond the paper (issue 35): written where set, so that default runs keep their study text
    if settings["sections"] != type(spec.settings).sections:
        numerics["sections"] = settings["sections"]
    if settings["detraining"] is not None:
        numerics["detraining"] = settings["detraining"]
    for name in ("fiber_growth", "fiber_tau", "fiber_crit", "stimulus"):
        if settings[name] != getattr(type(spec.settings), name):
            numerics[name] = settings[name]
    if spec.mesh is None and spec.quadrature_degree is not None:
        numerics["quadrature_degree"] = spec.quadrature_degree
    if spec.refine:
        numerics["refine"] = spec.refine
    lines += table("numerics", numerics)
    if spec.petsc_options:
        lines.append(f"# PETSc options of the mechanics solver (no study key sets them): {dict(spec.petsc_options)}")
    if spec.mesh is None and spec.fiber_data is not None:
        lines.append(f"# fibres from data: --fibers {spec.fiber_data.path.resolve()} (a study sets them on a [[mesh]] "
                     "only)")
    if spec.mesh is not None and spec.fibers not in ("auto", "data"):
        lines.append(f"# the mesh's fibres: --fibers {spec.fibers} (no study key sets them; a study's meshes "
                     "run their Stokes fibres)")
    return "\n".join(lines).rstrip() + "\n"
