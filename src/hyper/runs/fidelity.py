"""Scene-adaptive fidelity: the cheapest model and steps that answer a scene within an accuracy.

A scene is what a run is asked: on which geometry (none for a signaling question), under
which protocol, with uniform or per-cell (heterogeneous) signaling parameters, and about
what: the growth (CSA/CSA0, V/V0) or the signaling (N). `choose` picks the model the
scene needs and the longest growth and RK4 steps whose error, taken from the measured
error tables below, stays within the accuracy:

- The accuracy is relative to what is asked, as the benchmarks measure it:
  |x - x_ref| / (x_ref - 1) for x = CSA/CSA0 or V/V0 (a fraction of the growth: 1e-3 is
  0.1 %), |N - N_ref| / N_ref for a signaling question.
- A growth question has two error sources that add, the growth step and the RK4 step:
  each gets half of the accuracy. A signaling question has no growth step, and the RK4
  step gets all of it.
- The tables were measured on the idealized muscle under mwf; for other geometries and
  protocols they are an estimate (the reasons say so), which the safety factors cover.

The predicted error of a choice is the sum of the table's estimates, without the safety
factors; the choice keeps each estimate times its factor within its share.

The mesh (`spatial`, `choose_on_mesh`): the spatial discretisation error of the growth,
from the convergence tables below (`SPATIAL_ERROR`, measured by `python -m hyper.bench
convergence`), is a third source that adds to the other two. Every run's result records
it (`spatial(...).as_attributes()`, the result's ``spatial`` group). With an accuracy,
the mesh is chosen first: the fewest uniform refinements (``--refine K``, at least the K
given) whose spatial error is within `SPATIAL_SHARE` of the accuracy; the steps then
share what is left. Two parts of the error stay under refinement: the fibres' (a refined
mesh carries the loaded mesh's fibre field, `hyper.fem.fibers.carried`) and the surface's
(refining keeps the polyhedron, whose facets approximate the muscle's surface); an
accuracy below them is refused with what the mesh can give.

The linear solver is chosen once the mesh is known (`linear_solver`): MUMPS's LU on
meshes below `PMG_FASTER_FROM` unknowns while its memory, predicted from the measured
growth with the number of unknowns, fits in the memory available; "pmg" (GMRES, a Schur
fieldsplit with a P2 -> P1 multigrid, memory about linear in the mesh) from that size on,
where it is the faster, and wherever LU would not fit. Both answer to the Newton
tolerance, so the choice changes the cost, not the answer.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from hyper.core.params import InputError, as_attributes, finite, positive_hours, shown

ASKS = ("growth", "signaling")
MODELS = ("signaling-only", "uniform", "per-cell")
DEFAULT_ACCURACY = 1e-3  # 0.1 % of the growth

# Error of the growth from the growth step: |x - x_ref| / (x_ref - 1) at 9 weeks, the
# larger of x = CSA/CSA0 and V/V0, against Δtg = 0.5 h (idealized muscle, mwf, 1 rank),
# rounded up. Measured by `python -m hyper.bench growth` (results/bench/growth.json,
# sweep[].errors). 168 h is one step per period for the paper's protocols (the sweep's
# "1/period"). The 0.5 h reference's own error is unknown (the 1 h and 2 h errors are at
# round-off level and give no order), which GROWTH_SAFETY also covers.
GROWTH_STEP_ERROR = {1.0: 6.37e-8, 2.0: 6.88e-8, 6.0: 5.46e-7, 24.0: 2.86e-6, 168.0: 7.16e-6}
GROWTH_SAFETY = 10.0
GROWTH_SHARE = 0.5  # of a growth question's accuracy; the RK4 step gets the rest

# RK4 against DOP853 at rtol 1e-13 on mwf, measured by `python -m hyper.bench signaling`
# (results/bench/signaling.json, speed_accuracy): at dt = 0.05 h the relative error of
# N(1512 h) is 4.07e-7, the observed order 4 (6.2e-6 at 0.1 h, 1.1e-8 at 0.02 h), stable up
# to 0.65 h, failing from 0.7 h. Relative to the growth, N - 1, the same error is 4.87e-6
# (growth.json, paper_signaling_check). Both rounded up.
SIGNALING_DT0 = 0.05  # h, also the default step of hyper.signaling and GrowthSettings
SIGNALING_ERROR = {"signaling": 4.1e-7, "growth": 4.9e-6}  # at SIGNALING_DT0, by what is asked
SIGNALING_ORDER = 4
# The measured errors exceed the order-4 extrapolation from 0.05 h by up to 1.41x (at
# 0.4 h); with 2 every measured step up to 0.5 h lies within its prediction.
SIGNALING_SAFETY = 2.0
STABLE_DT = 0.65  # h, the largest RK4 step measured stable on mwf
# RK4 steps that divide the sessions (1 h, 4 h) and delays (12 h, 17 h) of the paper, so
# that RK4 shortens a step only to land on the end of the AKT bump (15.77 h after a
# session start) or on a sample time; the largest keeps clear of STABLE_DT (0.6 h already
# loses 2.6 % of N).
SIGNALING_LADDER = (0.01, 0.02, 0.025, 0.05, 0.1, 0.125, 0.25, 0.5)


@dataclass(frozen=True)
class Scene:
    """What a run is asked. ``protocol`` names the protocol (a command that runs several
    with one set of steps names them all, comma-separated)."""

    geometry: str | None  # None: no mesh
    protocol: str
    heterogeneous: bool  # per-cell signaling parameters
    ask: str  # "growth" or "signaling"

    def __post_init__(self):
        if self.ask not in ASKS:
            raise InputError(f"ask must be one of {', '.join(ASKS)}, got {self.ask!r}")
        if self.ask == "growth" and self.geometry is None:
            raise InputError("a growth question needs a geometry")


@dataclass(frozen=True)
class Choice:
    """The model and steps that answer a scene, their predicted error and why."""

    model: str  # one of MODELS
    growth_dt: float | None  # h, the longest growth step; None: nothing grows
    signaling_dt: float  # h, the RK4 step
    predicted_error: float  # in the accuracy's measure (of the growth, or of N)
    reasons: tuple[str, ...]
    accuracy: float | None = None  # asked for; None: the steps were given, not chosen
    refine: int | None = None  # uniform refinements chosen for the accuracy (`choose_on_mesh`); None: not chosen
    spatial_error: float | None = None  # the mesh's share of predicted_error; None: not counted
    linear_solver: str | None = None  # "lu" or "pmg" once the mesh is known
    linear_solver_reason: str | None = None

    def with_linear_solver(self, unknowns: int, available_mb: float) -> Choice:
        """This choice completed with the linear solver for a mesh (`linear_solver`)."""
        solver, why = linear_solver(unknowns, available_mb)
        return dataclasses.replace(self, linear_solver=solver, linear_solver_reason=why)

    def as_attributes(self) -> dict:
        """HDF5 attributes: the fields, without the unset ones, reasons as one text."""
        out = {k: v for k, v in as_attributes(self).items() if v is not None}
        out["reasons"] = "; ".join(self.reasons)
        return out

    def describe(self) -> str:
        steps = f"RK4 step {self.signaling_dt:g} h"
        if self.growth_dt is not None:
            steps = f"growth step {self.growth_dt:g} h, " + steps
        measure = "of N" if self.model == "signaling-only" else "of the growth"
        if self.accuracy is None:
            bound = "(no accuracy asked)"
        else:
            bound = f"{'<=' if self.predicted_error <= self.accuracy else '>'} accuracy {self.accuracy:g}"
        solver = "" if self.linear_solver is None else f"; linear solver {self.linear_solver}"
        if self.refine is not None:
            steps = f"mesh refined {self.refine} time(s) (spatial error {self.spatial_error:.2g}), " + steps
        return f"{self.model} model, {steps}; predicted error {self.predicted_error:.2g} {measure} {bound}{solver}"


def growth_step_error(dt: float) -> float:
    """The tabulated error of the growth for a growth step of ``dt`` h: that of the shortest
    tabulated step at least as long, or of one step per period beyond them."""
    longer = [step for step in GROWTH_STEP_ERROR if step >= dt]
    return GROWTH_STEP_ERROR[min(longer) if longer else max(GROWTH_STEP_ERROR)]


def signaling_error(dt: float, ask: str) -> float:
    """RK4's error for a step of ``dt`` h, extrapolated with its order from SIGNALING_DT0,
    relative to what ``ask`` asks (the growth, or N)."""
    return SIGNALING_ERROR[ask] * (dt / SIGNALING_DT0) ** SIGNALING_ORDER


def _shares(ask: str) -> tuple[float, float]:
    """(growth step, RK4 step) shares of the accuracy."""
    return (GROWTH_SHARE, 1.0 - GROWTH_SHARE) if ask == "growth" else (0.0, 1.0)


def smallest_accuracy(ask: str) -> float:
    """The tightest accuracy the tables can promise for a question about ``ask``."""
    growth_share, signaling_share = _shares(ask)
    least = SIGNALING_SAFETY * signaling_error(min(SIGNALING_LADDER), ask) / signaling_share
    if growth_share:
        least = max(least, GROWTH_SAFETY * min(GROWTH_STEP_ERROR.values()) / growth_share)
    return least


def _model(scene: Scene) -> tuple[str, str]:
    if scene.ask == "signaling":
        return "signaling-only", "a signaling question: the ODEs alone, no mesh"
    if scene.heterogeneous:
        return "per-cell", "heterogeneous parameters: one signaling ODE per cell"
    return "uniform", "uniform parameters: one signaling ODE for the whole muscle"


def _where(scene: Scene) -> tuple[str, ...]:
    if scene.ask == "signaling":
        if scene.protocol == "mwf":
            return ()
        return (f"the RK4 errors were measured on mwf; for {scene.protocol} they are an estimate",)
    if (scene.geometry, scene.protocol) == ("idealized", "mwf"):
        return ()
    return (f"the error tables were measured on idealized/mwf; for {scene.geometry}/{scene.protocol} "
            "they are an estimate",)


def _unstable(signaling_dt: float) -> tuple[str, ...]:
    if signaling_dt <= STABLE_DT:
        return ()
    return (f"RK4 step {signaling_dt:g} h is above {STABLE_DT:g} h, the largest measured stable on mwf",)


def _predicted(ask: str, growth_dt: float | None, signaling_dt: float) -> float:
    growth_part = 0.0 if growth_dt is None else growth_step_error(growth_dt)
    return growth_part + signaling_error(signaling_dt, ask)


def _check_steps(scene: Scene, growth_dt, signaling_dt) -> None:
    for name, value in (("growth_dt", growth_dt), ("signaling_dt", signaling_dt)):
        if value is not None:
            positive_hours(value, name)
    if scene.ask == "signaling" and growth_dt is not None:
        raise InputError("a signaling question has no growth step: give no growth_dt")


def choose(scene: Scene, accuracy: float = DEFAULT_ACCURACY, *, growth_dt: float | None = None,
           signaling_dt: float | None = None) -> Choice:
    """The cheapest model and longest steps that answer ``scene`` within ``accuracy``.

    A growth step or RK4 step given here is kept instead of the chosen one (the reasons
    say so, and the predicted error is that of the given step). Raises InputError for an
    accuracy that is not a finite number in (0, 0.5), or tighter than the tables promise.
    """
    if isinstance(accuracy, bool) or not isinstance(accuracy, (int, float)) or not (
        finite(accuracy) and 0 < accuracy < 0.5
    ):
        raise InputError(f"accuracy must be a finite number in (0, 0.5), a fraction of what is asked "
                         f"(1e-3 is 0.1 %), got {shown(accuracy)}")
    _check_steps(scene, growth_dt, signaling_dt)
    accuracy = float(accuracy)
    growth_share, signaling_share = _shares(scene.ask)
    growth_budget, signaling_budget = growth_share * accuracy, signaling_share * accuracy
    growth_steps = [dt for dt, e in GROWTH_STEP_ERROR.items() if GROWTH_SAFETY * e <= growth_budget]
    # safety error(dt) <= budget is dt <= 0.05 h (budget / (safety error(0.05 h)))^(1/4)
    rk4_steps = [dt for dt in SIGNALING_LADDER if SIGNALING_SAFETY * signaling_error(dt, scene.ask) <= signaling_budget]
    if not rk4_steps or (growth_share and not growth_steps):
        raise InputError(f"accuracy {accuracy:g} is tighter than the measured error tables can promise for a "
                         f"{scene.ask} question; the smallest supported accuracy is "
                         f"{smallest_accuracy(scene.ask):.3g}")
    model, why = _model(scene)
    reasons = [why, *_where(scene)]
    chosen_rk4 = max(rk4_steps)
    if growth_share:
        chosen_growth = max(growth_steps)
        reasons.append(f"accuracy {accuracy:g} of the growth split in half: {growth_budget:.3g} to the growth "
                       f"step, {signaling_budget:.3g} to the RK4 step")
        reasons.append(f"growth step {chosen_growth:g} h: the longest whose tabulated error "
                       f"{GROWTH_STEP_ERROR[chosen_growth]:.3g} x {GROWTH_SAFETY:g} <= {growth_budget:.3g} "
                       "(python -m hyper.bench growth)")
    else:
        chosen_growth = None
        reasons.append(f"accuracy {accuracy:g} of N, all of it to the RK4 step (nothing grows)")
    reasons.append(f"RK4 step {chosen_rk4:g} h: the largest of {', '.join(f'{dt:g}' for dt in SIGNALING_LADDER)} h "
                   f"(steps that divide the sessions, below the stability limit {STABLE_DT:g} h) whose error "
                   f"{signaling_error(chosen_rk4, scene.ask):.2g} x {SIGNALING_SAFETY:g} <= {signaling_budget:.3g} "
                   f"(order {SIGNALING_ORDER} from {SIGNALING_ERROR[scene.ask]:.2g} at {SIGNALING_DT0:g} h, "
                   "python -m hyper.bench signaling)")
    if growth_dt is not None:
        reasons.append(f"growth step {growth_dt:g} h given explicitly, kept instead of the chosen {chosen_growth:g} h")
        chosen_growth = float(growth_dt)
    if signaling_dt is not None:
        reasons.append(f"RK4 step {signaling_dt:g} h given explicitly, kept instead of the chosen {chosen_rk4:g} h")
        reasons.extend(_unstable(signaling_dt))
        chosen_rk4 = float(signaling_dt)
    return Choice(model, chosen_growth, chosen_rk4, _predicted(scene.ask, chosen_growth, chosen_rk4),
                  tuple(reasons), accuracy)


def assess(scene: Scene, growth_dt: float | None, signaling_dt: float) -> Choice:
    """The model of ``scene`` with the given steps and their predicted error (no accuracy
    asked, nothing chosen)."""
    _check_steps(scene, growth_dt, signaling_dt)
    if scene.ask == "growth" and growth_dt is None:
        raise InputError("a growth question needs a growth step")
    model, why = _model(scene)
    reasons = (why, *_where(scene), "steps given, no accuracy asked", *_unstable(signaling_dt))
    growth_dt = None if growth_dt is None else float(growth_dt)
    return Choice(model, growth_dt, float(signaling_dt), _predicted(scene.ask, growth_dt, signaling_dt), reasons)


# ----------------------------------------------------------------------- linear solver

# The memory MUMPS's LU used (INFOG 22, MB summed over 2 ranks) on the idealized shape
# refined once and twice, in the growth solve of `python -m hyper.bench solvers`
# (results/bench/solvers.json, levels[]): a power law through the two, m = a n^b.
LU_MEMORY_MB = ((78120, 871.0), (577993, 11946.0))  # exponent 1.31
# "pmg" (GMRES, Schur fieldsplit, P2 -> P1 multigrid): its peak resident memory (MB, summed
# over 2 ranks) in the same growth solve, at 578k unknowns; it grows as n^0.84 from 78k
# (python -m hyper.bench solvers --parts levels scaling --solvers pmg --output
# results/bench/scaling): taken as linear through the measurement, which overestimates
# below it and is exact at it.
PMG_MEMORY_MB = (577993, 3907.0)
# From this many unknowns pmg takes less time than LU. Measured in the growth solve of
# `python -m hyper.bench solvers --parts levels` (2 ranks, results/bench/scalable): pmg's
# time over LU's is 1.01 at 11k unknowns, 0.91 at 78k and 0.24 at 578k on the idealized
# shape, but 1.6 on TA_VHF_Left at 48k (1 rank, `--parts pmg`: anatomical meshes need more
# GMRES iterations); the threshold lies between the tie at 78k and the clear win at 578k.
PMG_FASTER_FROM = 300_000
# LU runs while its predicted memory is within this share of the memory available: the
# mesh, forms, fields and MUMPS's own workspace estimate (up to 20 % above its use) need the rest.
LU_MEMORY_SHARE = 0.7


def lu_memory_mb(unknowns: int) -> float:
    """MUMPS LU's memory (MB, all ranks together) for a Taylor–Hood system of ``unknowns``."""
    (n0, m0), (n1, m1) = LU_MEMORY_MB
    exponent = math.log(m1 / m0) / math.log(n1 / n0)
    return m1 * (unknowns / n1) ** exponent


def pmg_memory_mb(unknowns: int) -> float:
    """The "pmg" solver's peak memory (MB, all ranks together) for ``unknowns``."""
    n, m = PMG_MEMORY_MB
    return m * unknowns / n


def linear_solver(unknowns: int, available_mb: float) -> tuple[str, str]:
    """LU on small meshes while it fits in the memory available, else the pmg solver (at
    578k unknowns 0.24x LU's time and 0.24x its memory, in a growth solve on 2 ranks); and why."""
    lu = lu_memory_mb(unknowns)
    fits = lu <= LU_MEMORY_SHARE * available_mb
    if fits and unknowns < PMG_FASTER_FROM:
        return "lu", (f"MUMPS LU: {unknowns} unknowns need about {lu / 1024:.2g} GiB, within "
                      f"{LU_MEMORY_SHARE:g} x {available_mb / 1024:.3g} GiB available")
    pmg = pmg_memory_mb(unknowns)
    if fits:
        why = f"from {PMG_FASTER_FROM} unknowns on it is faster than LU ({unknowns} unknowns)"
    else:
        why = (f"LU would need about {lu / 1024:.3g} GiB for {unknowns} unknowns, more than "
               f"{LU_MEMORY_SHARE:g} x {available_mb / 1024:.3g} GiB available")
    left = "" if pmg <= LU_MEMORY_SHARE * available_mb else "; it may not fit either: use more nodes"
    return "pmg", f"GMRES with a multigrid fieldsplit (pmg): {why}; pmg needs about {pmg / 1024:.3g} GiB{left}"


# ------------------------------------------------------------------------ the mesh

MAX_REFINE = 3  # as runspec.MAX_REFINE (which imports this module)
SPATIAL_SHARE = 0.5  # of a growth question's accuracy the mesh may take; the steps share the rest


@dataclass(frozen=True)
class MeshError:
    """The measured spatial error of the growth on one geometry's default mesh: the larger
    of the CSA (cut) and volume gains' errors, as a fraction of the growth, after 9 weeks
    of mwf (`python -m hyper.bench convergence`, the own-fibre series at the level of
    the shipped mesh's size)."""

    error: float  # at the default mesh, refine 0
    # the part uniform refinement keeps: the fibres' resolution (a refined mesh carries the
    # loaded mesh's field) and the surface's facets (refining keeps the polyhedron)
    kept: float
    order: float  # of the rest, the finite elements' on the polyhedron, in h (--refine halves h)
    source: str  # the command and the level it was measured at
    # False: measured on another mesh of the geometry's surface (`hyper mesh`'s), so for
    # the shipped mesh an estimate
    same_mesh: bool = True


# The estimated error of the 8000-cell level (hyper mesh's default) of each muscle's
# `--all` study with the finest levels: (the largest of the CSA and volume gains' errors
# and the CSA gain's with the finest level's fibres, of the growth, two digits rounded up;
# the study's levels). Printed by `python -m hyper.bench convergence --spatial-table
# results/bench/convergence_quick results/bench/convergence_16k
# results/bench/convergence_32k results/bench/convergence_64k
# results/bench/convergence_full --output results/bench/spatial` from the studies of
# docs/convergence.md ("The spatial error of every muscle": 4k-32k cells, 8k-64k for
# three). Most have no asymptotic order: the error is the spread of the finest levels (and
# for the 8k level below a finer one, its distance to the finest plus that spread), a
# measure of the scatter, not a bound; the finest fibres' series counts too, since the own
# fibres' and the mechanics' changes can cancel. The levels are meshes of the muscle's STL
# by `hyper mesh` with its defaults (fibres smoothed over 2 mm, ends along the STL's axis);
# the shipped meshes are other meshes of the same surfaces (the 12 paper muscles:
# fTetWild's; the 19 others: `make new-meshes`, fibres unsmoothed), hence an estimate for
# them. No refinement of these was measured: all of it is taken as kept.
SURFACE_STUDIES = {
    "BFLH_VHF_Left": (0.0086, (4000, 8000, 16000, 32000)),
    "BFLH_VHM_Left": (0.0016, (4000, 8000, 16000, 32000)),
    "BFLH_VHM_Right": (0.0017, (4000, 8000, 16000, 32000)),
    "GM_VHF_Left": (0.0077, (4000, 8000, 16000, 32000)),
    "GM_VHF_Right": (0.015, (4000, 8000, 16000, 32000)),
    "GM_VHM_Left": (0.0016, (4000, 8000, 16000, 32000)),
    "GM_VHM_Right": (0.0072, (4000, 8000, 16000, 32000)),
    "RF_VHF_Left": (0.0044, (4000, 8000, 16000, 32000)),
    "RF_VHF_Right": (0.0026, (4000, 8000, 16000, 32000)),
    "RF_VHM_Left": (0.00024, (4000, 8000, 16000, 32000)),
    "ST_VHF_Left": (0.00082, (4000, 8000, 16000, 32000)),
    "ST_VHF_Right": (0.0009, (4000, 8000, 16000, 32000)),
    "ST_VHM_Left": (0.0028, (4000, 8000, 16000, 32000)),
    "ST_VHM_Right": (0.0011, (4000, 8000, 16000, 32000)),
    "TA_VHF_Left": (0.0026, (4000, 8000, 16000, 32000)),
    "TA_VHF_Right": (0.0046, (4000, 8000, 16000, 32000)),
    "TA_VHM_Left": (0.018, (8000, 16000, 32000, 64000)),
    "TA_VHM_Right": (0.0071, (4000, 8000, 16000, 32000)),
    "VI_VHF_Left": (0.011, (4000, 8000, 16000, 32000)),
    "VI_VHF_Right": (0.016, (4000, 8000, 16000, 32000)),
    "VI_VHM_Left": (0.0098, (4000, 8000, 16000, 32000)),
    "VI_VHM_Right": (0.025, (4000, 8000, 16000, 32000)),
    "VL_VHF_Left": (0.0084, (4000, 8000, 16000, 32000)),
    "VL_VHF_Right": (0.007, (4000, 8000, 16000, 32000)),
    "VL_VHM_Left": (0.13, (8000, 16000, 32000, 64000)),
    "VL_VHM_Right": (0.066, (8000, 16000, 32000, 64000)),
    "VM_VHF_Left": (0.00086, (4000, 8000, 16000, 32000)),
    "VM_VHF_Right": (0.0015, (4000, 8000, 16000, 32000)),
    "VM_VHM_Left": (0.00075, (4000, 8000, 16000, 32000)),
    "VM_VHM_Right": (0.0038, (4000, 8000, 16000, 32000)),
}


# The same with the Laplace fibres (`hyper mesh --method laplace`, `hyper.fem.laplace`): the
# studies of docs/convergence.md ("Laplace fibres"), `--fibres-method laplace --output
# results/bench/convergence_laplace`, printed by `--spatial-table results/bench/convergence_laplace`.
LAPLACE_STUDIES = {
    "BFLH_VHF_Left": (0.0039, (4000, 8000, 16000, 32000)),
    "BFLH_VHM_Left": (0.00041, (4000, 8000, 16000, 32000)),
    "BFLH_VHM_Right": (0.00059, (4000, 8000, 16000, 32000)),
    "GM_VHF_Left": (0.0027, (4000, 8000, 16000, 32000)),
    "GM_VHF_Right": (0.0033, (4000, 8000, 16000, 32000)),
    "GM_VHM_Left": (0.0009, (4000, 8000, 16000, 32000)),
    "GM_VHM_Right": (0.00036, (4000, 8000, 16000, 32000)),
    "RF_VHF_Left": (0.0026, (4000, 8000, 16000, 32000)),
    "RF_VHF_Right": (0.0025, (4000, 8000, 16000, 32000)),
    "RF_VHM_Left": (0.00039, (4000, 8000, 16000, 32000)),
    "ST_VHF_Left": (0.00057, (4000, 8000, 16000, 32000)),
    "ST_VHF_Right": (0.0002, (4000, 8000, 16000, 32000)),
    "ST_VHM_Left": (0.00031, (4000, 8000, 16000, 32000)),
    "ST_VHM_Right": (0.00052, (4000, 8000, 16000, 32000)),
    "TA_VHF_Left": (0.0019, (4000, 8000, 16000, 32000)),
    "TA_VHF_Right": (0.0029, (4000, 8000, 16000, 32000)),
    "TA_VHM_Left": (0.0019, (4000, 8000, 16000, 32000)),
    "TA_VHM_Right": (0.0049, (4000, 8000, 16000, 32000)),
    "VI_VHF_Left": (0.00076, (4000, 8000, 16000, 32000)),
    "VI_VHF_Right": (0.0011, (4000, 8000, 16000, 32000)),
    "VI_VHM_Left": (0.0017, (4000, 8000, 16000, 32000)),
    "VI_VHM_Right": (0.0002, (4000, 8000, 16000, 32000)),
    "VL_VHF_Left": (0.002, (4000, 8000, 16000, 32000)),
    "VL_VHF_Right": (0.0024, (4000, 8000, 16000, 32000)),
    "VL_VHM_Left": (0.00031, (4000, 8000, 16000, 32000)),
    "VL_VHM_Right": (0.0012, (4000, 8000, 16000, 32000)),
    "VM_VHF_Left": (0.00043, (4000, 8000, 16000, 32000)),
    "VM_VHF_Right": (0.00087, (4000, 8000, 16000, 32000)),
    "VM_VHM_Left": (8.7e-05, (4000, 8000, 16000, 32000)),
    "VM_VHM_Right": (0.00081, (4000, 8000, 16000, 32000)),
}


def _surface_entry(muscle: str, error: float, levels: tuple[int, ...], fibres: str = "stokes") -> MeshError:
    cells = " ".join(map(str, levels))
    return MeshError(error, error, 1.0, f"python -m hyper.bench convergence --all {muscle} --cells {cells} "
                     f"--fibres-method {fibres}: the 8000-cell level of hyper mesh's meshes of its surface",
                     same_mesh=False)


# Rounded up; measured as the source says. The idealized shape's, against its mesh refined
# once (analytic fibres evaluated on each mesh: no fibre share), gives no order: 1, slower
# than any measured (the end force's is 1.8, python -m hyper.bench refinement), is assumed.
# Two muscles measured before the fibres were smoothed keep those measurements, taken with
# the fibre rules of the shipped meshes, where they are the larger (GM_VHF_Left's, 3.4e-3,
# is not). TA_VHF_Left's separates a finite elements' part, from the 4k level refined once
# (`hyper grow --mesh … --refine 1`: the CSA gain moves by 1.5e-3 of the growth, order 1
# assumed, scaled to the 8k level's h); docs/convergence.md.
SPATIAL_ERROR = {
    "idealized": MeshError(1.5e-4, 0.0, 1.0, "python -m hyper.bench atlas: the mesh as given against refined once"),
    **{muscle: _surface_entry(muscle, error, levels) for muscle, (error, levels) in SURFACE_STUDIES.items()},
    "TA_VHF_Left": MeshError(4.6e-3, 2.0e-3, 1.0, "python -m hyper.bench convergence TA_VHF_Left --quick "
                             "--fibres-method stokes, unsmoothed fibres: the CSA gain's spread between the 4k and 8k "
                             "meshes of its surface",
                             same_mesh=False),
    "ST_VHM_Right": MeshError(2.7e-3, 2.7e-3, 1.0, "python -m hyper.bench convergence ST_VHM_Right --quick "
                              "--fibres-method stokes, unsmoothed fibres: the CSA gain's spread between the 4k and 8k "
                              "meshes of its surface",
                              same_mesh=False),
}


# by fibre kind (what the fibre file beside a mesh file says it holds): the kinds without a
# table of their own (pennate, from data) take the Stokes fibres' table
LAPLACE_ERROR = {muscle: _surface_entry(muscle, error, levels, "laplace")
                 for muscle, (error, levels) in LAPLACE_STUDIES.items()}
TABLES = {"stokes": SPATIAL_ERROR, "laplace": LAPLACE_ERROR}


# Each shipped geometry's own mesh with its fibres (by kind) made on it, against the limit of
# the study of its surface (LAPLACE_STUDIES', SURFACE_STUDIES'; BFLH_VHF_Right, without a
# surface, its other side's): the larger of the CSA and volume gains' errors, of the growth,
# rounded up, measured on the very mesh a --geometry run uses. Printed by `python -m
# hyper.bench convergence --shipped --fibres-method laplace --output results/bench/shipped`
# (and --fibres-method stokes --studies with the Stokes studies' folders, docs/convergence.md).
# The 12 paper muscles' fTetWild meshes are not the studies' levels: TA_VHF_Left's CSA is
# 5.3e-3 of the growth from the limit on its vertices' plane, 5.0e-4 on the solid's plane.
SHIPPED_STUDIES = {
    "laplace": {
        "BFLH_VHF_Left": 0.0034,
        "BFLH_VHF_Right": 0.0022,
        "BFLH_VHM_Left": 0.0019,
        "BFLH_VHM_Right": 0.00045,
        "ST_VHF_Left": 0.0025,
        "ST_VHF_Right": 0.0029,
        "ST_VHM_Left": 0.00099,
        "ST_VHM_Right": 0.00029,
        "TA_VHF_Left": 0.0054,
        "TA_VHF_Right": 0.0044,
        "TA_VHM_Left": 0.0037,
        "TA_VHM_Right": 0.0022,
        "GM_VHF_Left": 0.0024,
        "GM_VHF_Right": 0.0032,
        "GM_VHM_Left": 0.00085,
        "GM_VHM_Right": 0.00026,
        "RF_VHF_Left": 0.0025,
        "RF_VHF_Right": 0.0023,
        "RF_VHM_Left": 0.00028,
        "VI_VHF_Left": 0.00033,
        "VI_VHF_Right": 0.00073,
        "VI_VHM_Left": 0.0014,
        "VI_VHM_Right": 5.5e-05,
        "VL_VHF_Left": 0.0018,
        "VL_VHF_Right": 0.0024,
        "VL_VHM_Left": 0.00026,
        "VL_VHM_Right": 0.00081,
        "VM_VHF_Left": 0.00038,
        "VM_VHF_Right": 0.0007,
        "VM_VHM_Left": 4.1e-05,
        "VM_VHM_Right": 0.00078,
    },
    "stokes": {
        "BFLH_VHF_Left": 0.0047,
        "BFLH_VHF_Right": 0.0056,
        "BFLH_VHM_Left": 0.0026,
        "BFLH_VHM_Right": 0.0039,
        "ST_VHF_Left": 0.0016,
        "ST_VHF_Right": 0.0088,
        "ST_VHM_Left": 0.0044,
        "ST_VHM_Right": 0.003,
        "TA_VHF_Left": 0.016,
        "TA_VHF_Right": 0.0068,
        "TA_VHM_Left": 0.016,
        "TA_VHM_Right": 0.0048,
        "GM_VHF_Left": 0.0057,
        "GM_VHF_Right": 0.00074,
        "GM_VHM_Left": 0.0017,
        "GM_VHM_Right": 0.0057,
        "RF_VHF_Left": 0.0033,
        "RF_VHF_Right": 0.0066,
        "RF_VHM_Left": 0.00096,
        "VI_VHF_Left": 0.012,
        "VI_VHF_Right": 0.0021,
        "VI_VHM_Left": 0.0035,
        "VI_VHM_Right": 0.024,
        "VL_VHF_Left": 0.009,
        "VL_VHF_Right": 0.0097,
        "VL_VHM_Left": 0.14,
        "VL_VHM_Right": 0.069,
        "VM_VHF_Left": 0.0014,
        "VM_VHF_Right": 0.00049,
        "VM_VHM_Left": 0.00059,
        "VM_VHM_Right": 0.0023,
    },
}


def other_side(geometry: str) -> str:
    """'BFLH_VHF_Right' -> 'BFLH_VHF_Left' (and back); any other name as it is."""
    *rest, side = geometry.split("_")
    other = {"Left": "Right", "Right": "Left"}.get(side)
    return "_".join([*rest, other]) if other and rest else geometry


def _shipped_entry(name: str, measured: float, kind: str) -> MeshError:
    """The larger of the shipped mesh's measured error and its surface's 8k-level entry (its
    other side's for BFLH_VHF_Right), which counts the finest fibres' series where the own
    fibres' and the mechanics' changes cancel (SPATIAL_ERROR's comment)."""
    muscle = name if name in TABLES[kind] else other_side(name)
    surface = TABLES[kind][muscle]
    error = max(measured, surface.error)
    return MeshError(error, error, 1.0, f"python -m hyper.bench convergence --shipped {name} --fibres-method {kind}: "
                     f"its shipped mesh against {muscle}'s surface's limit, {measured:.2g} of the growth; with that "
                     f"study's {surface.error:.2g} at its 8000-cell level, the larger")


SHIPPED_ERROR = {kind: {name: _shipped_entry(name, error, kind) for name, error in table.items()}
                 for kind, table in SHIPPED_STUDIES.items()}


@dataclass(frozen=True)
class Spatial:
    """The spatial error of the growth on a geometry refined ``refine`` times, and whence."""

    geometry: str
    refine: int
    error: float  # fraction of the growth
    kept: float  # of which what refining keeps (`MeshError.kept`)
    measured: bool  # False: estimated from another geometry's table
    reason: str

    def as_attributes(self) -> dict:
        return as_attributes(self)

    def describe(self) -> str:
        est = "" if self.measured else ", estimated"
        return (f"spatial error {self.error:.2g} of the growth{est} ({self.kept:.2g} of it kept under --refine: "
                f"fibres and surface facets; {self.reason})")


def _table_entry(geometry: str, mesh_file: bool, fibres: str = "stokes") -> tuple[MeshError, bool, str]:
    if not mesh_file and geometry in SHIPPED_ERROR.get(fibres, {}):
        entry = SHIPPED_ERROR[fibres][geometry]
        return entry, True, entry.source
    if fibres != "stokes" and TABLES.get(fibres):
        return _kind_entry(geometry, TABLES[fibres], fibres, mesh_file)
    if not mesh_file and geometry in SPATIAL_ERROR:
        entry = SPATIAL_ERROR[geometry]
        return entry, entry.same_mesh, entry.source
    anatomical = {k: v for k, v in SPATIAL_ERROR.items() if k != "idealized"}
    mirror = other_side(geometry)
    if not mesh_file and mirror in anatomical:  # BFLH_VHF_Right has no surface to study
        entry = anatomical[mirror]
        return entry, False, f"no table for {geometry}: the other side's, {mirror}'s ({entry.source})"
    if geometry == "cylinder" and not mesh_file:
        entry = SPATIAL_ERROR["idealized"]
        return entry, False, f"no table for the cylinder: the idealized shape's ({entry.source})"
    if not anatomical:
        entry = SPATIAL_ERROR["idealized"]
        return entry, False, f"no anatomical table: the idealized shape's ({entry.source})"
    name, entry = max(anatomical.items(), key=lambda item: item[1].error)
    what = "a mesh file" if mesh_file else geometry
    return entry, False, (f"no table for {what}: the largest measured, {name}'s ({entry.source}); measure "
                          f"yours: python -m hyper.bench convergence SURFACE.stl --quick --fibres-method stokes")


def _kind_entry(geometry: str, table: dict, fibres: str, mesh_file: bool) -> tuple[MeshError, bool, str]:
    """A mesh with fibres of a kind that has a table of its own: a built-in geometry's muscle
    (a mesh of its surface by `hyper mesh`, so for the shipped mesh an estimate) or its other
    side's; a mesh file, or a geometry without either, the largest measured."""
    if not mesh_file:
        for name, whose in ((geometry, ""), (other_side(geometry), "the other side's, ")):
            if name in table:
                return table[name], False, f"{fibres} fibres: {whose}{name}'s ({table[name].source})"
    name, entry = max(table.items(), key=lambda item: item[1].error)
    what = "a mesh file" if mesh_file else geometry
    return entry, False, (f"{fibres} fibres, no table for {what}: the largest measured with them, {name}'s "
                          f"({entry.source}); measure yours: python -m hyper.bench convergence SURFACE.stl "
                          f"--fibres-method {fibres}")


def spatial(geometry: str, refine: int = 0, *, mesh_file: bool = False, fibres: str = "stokes") -> Spatial:
    """The spatial error of the growth on ``geometry`` (a built-in id, or with
    ``mesh_file`` the stem of a user's mesh) refined ``refine`` times: the table's fibre
    share that refining keeps plus the rest times 2^(-order refine). ``fibres``: the kind
    the mesh's fibre file holds (`TABLES`)."""
    entry, measured, why = _table_entry(geometry, mesh_file, fibres)
    elements = max(0.0, entry.error - entry.kept) * 2.0 ** (-entry.order * refine)
    return Spatial(geometry, int(refine), entry.kept + elements, entry.kept, measured, why)


def choose_on_mesh(scene: Scene, accuracy: float = DEFAULT_ACCURACY, *, refine: int = 0, mesh_file: bool = False,
                   fibres: str = "stokes", growth_dt: float | None = None, signaling_dt: float | None = None
                   ) -> Choice:
    """`choose` for a growth question with its mesh counted: the fewest refinements from
    ``refine`` up to MAX_REFINE whose spatial error is within SPATIAL_SHARE of
    ``accuracy``, then the steps for what is left. Raises InputError (one line: what the
    mesh can give) where none is."""
    if scene.ask != "growth":
        raise InputError("the mesh counts for a growth question only")
    choose(scene, accuracy, growth_dt=growth_dt, signaling_dt=signaling_dt)  # the accuracy's own checks
    candidates = [spatial(scene.geometry, k, mesh_file=mesh_file, fibres=fibres) for k in range(refine, MAX_REFINE + 1)]
    fitting = [c for c in candidates if c.error <= SPATIAL_SHARE * accuracy]
    if not fitting:
        best = candidates[-1]
        raise InputError(
            f"accuracy {accuracy:g} is tighter than the mesh of {scene.geometry} can give: its spatial error is "
            f"{best.error:.2g} of the growth even refined {best.refine} time(s), {best.kept:.2g} of it from the "
            f"fibres and the surface's facets, which --refine keeps ({best.reason}); the smallest supported "
            f"accuracy is {best.error / SPATIAL_SHARE:.2g}")
    mesh = fitting[0]
    steps = choose(scene, accuracy - mesh.error, growth_dt=growth_dt, signaling_dt=signaling_dt)
    estimated = "" if mesh.measured else " (an estimate)"
    reasons = (steps.reasons[0], f"mesh refined {mesh.refine} time(s): the fewest from {refine} whose spatial error "
               f"{mesh.error:.2g}{estimated} <= {SPATIAL_SHARE:g} x accuracy {accuracy:g} ({mesh.reason}; python -m "
               f"hyper.bench convergence); the steps get the rest, {accuracy - mesh.error:.3g}", *steps.reasons[1:])
    return dataclasses.replace(steps, accuracy=accuracy, refine=mesh.refine, spatial_error=mesh.error,
                               predicted_error=steps.predicted_error + mesh.error, reasons=reasons)
