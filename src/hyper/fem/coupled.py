"""The coupled model of MODEL.md §4: signaling ⇄ growth ⇄ mechanics.

`CoupledModel.run()` walks the protocol period by period (each session, and each rest
between sessions). For a period it advances the signaling ODEs with the current
synthesis rate kM, sampling the states at the ends of the growth steps; then, step by
step, it turns the population change dN into an area multiplier, updates the total
growth tensor, solves equilibrium from the previous solution, measures CSA and volume
and updates kM = kM0 h(CSA/CSA0) for the next period. It writes no files: it yields
one `StepReport` per growth step, and the caller decides what to keep.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from hyper.core.params import InputError, as_float, as_int, positive_hours
from hyper.fem import boxsection as box
from hyper.fem import growthfield, section, stimulus
from hyper.fem.mechanics import MechanicsProblem, SolverError
from hyper.fem.newton import KeptFactors, LaggedJacobian, NoTiming
from hyper.model import growth, signaling
from hyper.model.failure import GrowthFailure
from hyper.model.protocols import Protocol
from hyper.model.signaling import SignalingError

CSA_METHODS = ("cut", "box", "solid")


@dataclass(frozen=True)
class GrowthSettings:
    # h, longest growth step; periods are cut into steps no longer. 168 h is one step per
    # period for the paper protocols: 7e-6 of the growth from the 0.5 h answer (bench growth).
    growth_dt: float = 168.0
    signaling_dt: float = 0.05  # h, RK4 step of the signaling ODEs
    feedback: str = "hill"  # h(CSA/CSA0): hill, linear or none
    grow_during_sessions: bool = True  # False reproduces the original code
    consistent_stress: bool = True  # P = det(Fg) Fe S Fg⁻ᵀ; False: the original Fe S
    max_halvings: int = 4  # growth-step cuts tried before a failed solve stops the run
    # where G, Ḡ and A live: "quadrature" points, or "dg1" nodes (the original code)
    growth_fields: str = "quadrature"
    # CSA of a mesh without a tagged mid-section, the one the feedback sees: "cut" (the
    # exact cut by the vertices' plane, MODEL §4), "box" (the original code's staircase,
    # MODEL §9) or "solid" (the exact cut by the solid's plane, `PlaneSection`). All are
    # recorded either way; a tagged section (idealized, cylinder) is measured on its facets.
    csa_method: str = "cut"
    # How each step's equilibrium is solved: "kept" (factors kept across steps,
    # hyper.fem.newton) or "lagged" (SNES Newton with a lagged Jacobian, before issue 17).
    # Both stop at the same Newton tolerances, so this is not part of the answer.
    newton: str = "kept"
    # the signaling integrator (signaling.METHODS): rk4, or the original's RK45 and N0 (MODEL.md §9)
    signaling_method: str = "rk4"
    # dN of a growth step (growth.INCREMENTS): exact, N's change over the step; left-point,
    # f at the step's start times Δtg (the original code)
    growth_increment: str = "exact"
    # CSA at this many sections along the principal axis, at j/(K+1) of the length (9: 10 %, …,
    # 90 %), beside the mid-belly series: a measure only, the feedback sees the mid-belly CSA. 0: none.
    sections: int = section.SECTIONS
    # h, the time constant of the turnover of the gain (`hyper.model.growth.detrained`); None:
    # none, the paper's model, where a gain is kept for ever
    detraining: float | None = None
    # along-fibre growth (growth.FIBER_GROWTH): "none", the paper's transverse growth; "stretch",
    # ϑ_f of `hyper.model.growth.fibre_stretch_step` during the sessions that carry a stretch, with
    # its time constant (h) and homeostatic elastic fibre stretch. Illustrative values, not calibrated.
    fiber_growth: str = "none"
    fiber_tau: float = 168.0
    fiber_crit: float = 1.0
    # the exercise stimulus (stimulus.STIMULI): "global", the paper's one β I Fmax for every cell;
    # "local", each cell's scaled by its active fibre stress in the session's contraction
    # (`hyper.fem.stimulus`), normalised to a volume-weighted mean of 1
    stimulus: str = "global"
    preset: str = "default"  # the --settings preset these came from (hyper.runs.presets): a label

    # A step cut k times is 2^k solves: beyond this a run is better stopped and looked at.
    MAX_HALVINGS = 12
    # Settings added after results existed: in the digest only where they differ from their
    # defaults, so that the digests (and checkpoints) of default runs stay valid.
    DIGEST_IF_CHANGED = ("signaling_method", "growth_increment", "growth_fields", "csa_method", "sections",
                         "detraining", "fiber_growth", "fiber_tau", "fiber_crit", "stimulus")

    def __post_init__(self):
        positive_hours(self.growth_dt, "growth_dt", signaling.SMALLEST_DT)
        positive_hours(self.signaling_dt, "signaling_dt", signaling.SMALLEST_DT)
        if self.signaling_dt > self.growth_dt:
            raise InputError(f"{self.signaling_dt:g} h must not exceed the growth step ({self.growth_dt:g} h)",
                             field="signaling_dt")
        if self.feedback not in growth.FEEDBACK_LAWS:
            raise InputError(f"must be one of {', '.join(growth.FEEDBACK_LAWS)}, got {self.feedback!r}",
                             field="feedback")
        if self.newton not in NEWTON_METHODS:
            raise InputError(f"must be one of {', '.join(NEWTON_METHODS)}, got {self.newton!r}", field="newton")
        if self.growth_fields not in growthfield.GROWTH_FIELDS:
            raise InputError(f"must be one of {', '.join(growthfield.GROWTH_FIELDS)}, got {self.growth_fields!r}",
                             field="growth_fields")
        if self.csa_method not in CSA_METHODS:
            raise InputError(f"must be one of {', '.join(CSA_METHODS)}, got {self.csa_method!r}",
                             field="csa_method")
        if isinstance(self.max_halvings, bool) or not (
            isinstance(self.max_halvings, int) and 0 <= self.max_halvings <= self.MAX_HALVINGS
        ):
            raise InputError(f"must be an integer in [0, {self.MAX_HALVINGS}], got {self.max_halvings!r}",
                             field="max_halvings")
        signaling.integrator(self.signaling_method)  # validates it
        if self.growth_increment not in growth.INCREMENTS:
            raise InputError(f"must be one of {', '.join(growth.INCREMENTS)}, got {self.growth_increment!r}",
                             field="growth_increment")
        as_int(self.sections, "sections", 0, section.MAX_SECTIONS)
        if self.detraining is not None:
            positive_hours(self.detraining, "detraining")
        if self.fiber_growth not in growth.FIBER_GROWTH:
            raise InputError(f"must be one of {', '.join(growth.FIBER_GROWTH)}, got {self.fiber_growth!r}",
                             field="fiber_growth")
        positive_hours(self.fiber_tau, "fiber_tau")
        as_float(self.fiber_crit, "fiber_crit", 1.0)
        if self.stimulus not in stimulus.STIMULI:
            raise InputError(f"must be one of {', '.join(stimulus.STIMULI)}, got {self.stimulus!r}", field="stimulus")

    def model_attributes(self) -> dict:
        """The settings that define the solution; max_halvings only decides how hard a
        failing step is tried, so a stopped run may be resumed with another value, newton
        how the same equilibrium is found, and the preset only names where the values
        came from."""
        out = dataclasses.asdict(self)
        del out["max_halvings"], out["newton"], out["preset"]
        for name in self.DIGEST_IF_CHANGED:
            if out[name] == getattr(GrowthSettings, name):
                del out[name]
        return out


# Growth steps change the equilibrium by a fraction of a percent, so a Jacobian (and its
# LU factors) stays a good Newton matrix for many steps: refreshing it every 10
# iterations made the 9-week idealized run 4.8× faster with the same CSA to 1e-11.
# `hyper.fem.newton.LaggedJacobian` applies the lag; snes_lag_jacobian (in petsc_options or as
# -mechanics_snes_lag_jacobian) sets it and never reaches PETSc.
JACOBIAN_LAG = 10
LAG_OPTION = "snes_lag_jacobian"
NEWTON_METHODS = ("kept", "lagged")


# The phases a model times through its monitor. "jacobian assembly", "residual
# assembly", "factorisation" and "back-solves" happen inside "mechanics" (the Newton
# solves; the last two are timed with kept factors only: SNES does them inside PETSc);
# the others do not overlap.
PHASES = ("signaling", "mechanics", "jacobian assembly", "residual assembly", "factorisation", "back-solves",
          "growth update", "measures")


@dataclass
class StepReport:
    step: int  # growth steps done (0: the initial state)
    t: float  # h
    csa_ratio: float  # CSA/CSA0
    volume_ratio: float  # V/V0
    kM: float  # 1/h, synthesis rate after the feedback of this step
    states: np.ndarray  # (5,) signaling states (cell means in the heterogeneous case)
    newton_iterations: int
    halvings: int = 0
    extra: dict = field(default_factory=dict)
    sections: np.ndarray | None = None  # CSA/CSA0 at each regional section (None: none measured)



class PlaneSection:
    """The mid-belly cross-section of a mesh without a tagged one (MODEL §4), measured
    three ways: "cut", the plane through the mean of all vertices, normal to their first
    principal axis, cut exactly through the tetrahedra; "box", the original code's
    staircase (`hyper.box`, MODEL §9); "solid", the exact cut by the plane through the
    solid's centroid normal to its axis of inertia (`section.solid_plane`), which any mesh
    of one shape shares, where the vertices' plane moves with where the mesher put them
    (TA_VHM_Right: CSA0 10.60, 9.91, 10.23, 10.39 cm² on four meshes of its surface, the
    solid's 10.25-10.17; docs/convergence.md). The deformed area is Nanson's integral."""

    def __init__(self, problem: MechanicsProblem):
        mesh = problem.geometry.mesh
        degree = problem.geometry.quadrature_degree
        origin, normal = section.principal_plane(section.global_vertices(mesh, mesh.comm))
        self._cuts = {"cut": section.CutSection(mesh, origin, normal, degree=degree),
                      "solid": section.CutSection(mesh, *section.solid_plane(mesh), degree=degree)}
        # All evaluate u from a plain vector function: keep a collapsed copy of u.
        self._w = problem.w
        self.u, self._map = problem.w.function_space.sub(0).collapse()
        self.u = fem.Function(self.u)
        self.box = box.BoxSection(mesh, self.u)
        self.areas0 = {"cut": self._cuts["cut"].area0(), "box": self.box.area0(),
                       "solid": self._cuts["solid"].area0()}

    def ratios(self) -> dict[str, float]:
        """CSA/CSA0 by each method."""
        self.u.x.array[:] = self._w.x.array[self._map]
        return {"cut": self._cuts["cut"].deformed_area(self.u) / self.areas0["cut"],
                "box": self.box.deformed_area() / self.areas0["box"],
                "solid": self._cuts["solid"].deformed_area(self.u) / self.areas0["solid"]}


class RegionalSections:
    """The CSA at ``fractions`` of the length along the principal axis (``settings.sections``
    of them, `section.AxialSections`), each cut exactly; the deformed area by Nanson."""

    def __init__(self, problem: MechanicsProblem, fractions):
        mesh = problem.geometry.mesh
        self._cuts = section.AxialSections(mesh, fractions, degree=problem.geometry.quadrature_degree)
        self.fractions = self._cuts.fractions
        self.areas0 = self._cuts.areas0
        self._w = problem.w
        space, self._map = problem.w.function_space.sub(0).collapse()
        self.u = fem.Function(space)

    def ratios(self) -> np.ndarray:
        """CSA/CSA0 at each section."""
        self.u.x.array[:] = self._w.x.array[self._map]
        return self._cuts.deformed_areas(self.u) / self.areas0


@dataclass
class State:
    """A model's state for a checkpoint (`CoupledModel.state`): the original (mesh file)
    index of each owned cell, arrays with one row per owned cell, in that order, and
    values equal on every rank."""

    original: np.ndarray
    per_cell: dict[str, np.ndarray]
    glob: dict[str, Any]


def local_original_cells(mesh) -> np.ndarray:
    """The original (mesh file) index of each local cell, owned then ghost."""
    imap = mesh.topology.index_map(mesh.topology.dim)
    return np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[: imap.size_local + imap.num_ghosts]


class CoupledModel:
    """Owns the signaling state of one run and the parts it steps: the mechanics
    ``problem`` (`MechanicsProblem`), the ``growth_field`` (`growthfield.GrowthField`, its
    deformation set to the problem's F), the ``section`` that measures the CSA
    (`growthfield.FacetSection` or `PlaneSection`) and the ``jacobian`` that solves each
    step (`hyper.fem.newton.KeptFactors` or `LaggedJacobian`, as ``settings.newton`` says).
    `build_model` assembles the default parts.

    ``integrator`` advances the signaling ODEs, with the signature of
    `signaling.integrate` (default: ``settings.signaling_method``'s); ``monitor`` times
    the `PHASES` of the run (default `NoTiming`; the jacobian's should be the same).
    ``stimulus_factors`` (session intensity → one factor per owned cell; None: the global
    stimulus) scale each cell's β, so that it runs its own ODE: one intensity's in the parameters,
    several through `stimulus.SessionFactors` around the integrator; ``stimulus_record`` says how
    they were had (`stimulus.session_factors`).
    """

    def __init__(
        self,
        problem: MechanicsProblem,
        growth_field: growthfield.GrowthField,
        section,
        jacobian,
        protocol: Protocol,
        *,
        params: signaling.SignalingParams | None = None,
        settings: GrowthSettings = GrowthSettings(),
        integrator: Callable | None = None,
        monitor=None,
        regional: RegionalSections | None = None,
        stimulus_factors: dict[float, np.ndarray] | None = None,
        stimulus_record: dict | None = None,
    ):
        self.geometry = problem.geometry
        self.comm = self.geometry.mesh.comm
        self.protocol = protocol
        self.params = params if params is not None else signaling.SignalingParams()
        self.settings = settings
        self.integrator = integrator if integrator is not None else signaling.integrator(settings.signaling_method)
        # local mechanosensing: each owned cell's stimulus factor per session intensity (None: global).
        # The first one's scales β in the parameters, which makes the ODEs per cell and the
        # checkpoint carry it; with several, the integrator swaps them in session by session.
        self.stimulus_factors = stimulus_factors
        self.stimulus_record = dict(stimulus_record or {})  # how they were had: result attributes
        if stimulus_factors:
            beta = self.params.beta
            if len(stimulus_factors) > 1:
                self.integrator = stimulus.SessionFactors(self.integrator, beta, stimulus_factors)
            first = next(iter(stimulus_factors.values()))
            self.params = dataclasses.replace(self.params, beta=beta * np.asarray(first))
        self.monitor = monitor if monitor is not None else NoTiming()
        self.growth = growth_field
        self.problem = problem
        self.jacobian = jacobian
        self.section = section
        if isinstance(section, PlaneSection):
            self.csa0 = section.areas0[settings.csa_method]
        else:
            self.csa0 = section.area0
        # CSA0 (m²) and CSA/CSA0 by every method of a plane section (none for a tagged one)
        self.csa0_by_method = dict(self.section.areas0) if isinstance(self.section, PlaneSection) else {}
        self.csa_ratios = dict.fromkeys(self.csa0_by_method, 1.0)
        self.volume0 = self.problem.volume()
        # the regional sections (None: not measured) and their CSA/CSA0
        self.regional = regional
        self.section_ratios = None if regional is None else np.ones(len(regional.fractions))

        # Every run starts from the rest state of the baseline parameters (MODEL §1).
        # Per-cell parameters (one member per owned cell) give one ODE per cell, and ϑ,
        # G and Ḡ per cell; uniform parameters need one ODE for the whole body.
        rest = signaling.start_state(settings.signaling_method)
        n = self.params.size
        if n is None:
            self.y = rest
        elif n == len(self.growth.cells):
            self.y = np.repeat(rest[:, None], n, axis=1)
        else:
            raise InputError(
                f"per-cell signaling parameters need one value per owned cell "
                f"({len(self.growth.cells)} on rank {self.comm.rank}), got {n}"
            )
        self.kM0 = self.params.kM
        self.kM = self.kM0
        # ϑ_f, the along-fibre growth so far (settings.fiber_growth "stretch"; 1: none)
        self.fiber_growth = 1.0
        self.csa_ratio = 1.0
        self.volume_ratio = 1.0
        self.step = 0
        self.t = 0.0
        # Position in the protocol: the period being stepped through, the growth steps
        # of it already done, its signaling samples (None until it is integrated) and
        # the synthesis rate they were integrated with.
        self.period = 0
        self.period_step = 0
        self.period_times: np.ndarray | None = None
        self.period_states: np.ndarray | None = None
        self.period_kM = self.kM
        self.resumed = False

    def local_original_cells(self) -> np.ndarray:
        """The original (mesh file) index of each local cell, owned then ghost: what
        `hyper.runs.checkpoint.read` needs to send this rank the rows of its cells."""
        return local_original_cells(self.geometry.mesh)

    def _mean_states(self, y) -> np.ndarray:
        if y.ndim == 1:
            return y.copy()
        total = self.comm.allreduce(y.sum(axis=1), op=MPI.SUM)
        count = self.comm.allreduce(y.shape[1], op=MPI.SUM)
        return total / count

    def _report(self, iterations: int, halvings: int = 0) -> StepReport:
        return StepReport(
            step=self.step,
            t=self.t,
            csa_ratio=self.csa_ratio,
            volume_ratio=self.volume_ratio,
            kM=float(np.mean(self.kM)),
            states=self._mean_states(self.y),
            newton_iterations=iterations,
            halvings=halvings,
            extra=self._extra(),
            sections=None if self.section_ratios is None else self.section_ratios.copy(),
        )

    def _extra(self) -> dict:
        extra = {f"csa_ratio_{name}": value for name, value in self.csa_ratios.items()}
        if self.settings.fiber_growth != "none":
            extra["fiber_stretch"] = self.growth.mean_fibre_stretch()
        return extra

    @property
    def measures(self) -> tuple[str, ...]:
        """The names of the measures each `StepReport.extra` carries: the CSA by each method
        of a plane section, and with along-fibre growth ``fiber_stretch``, the fascicle length
        change a0·Ḡ a0 (`growthfield.GrowthField.mean_fibre_stretch`)."""
        names = tuple(f"csa_ratio_{name}" for name in self.csa_ratios)
        return (*names, "fiber_stretch") if self.settings.fiber_growth != "none" else names

    def _measure_csa(self) -> None:
        if self.csa_ratios:
            self.csa_ratios = self.section.ratios()
            self.csa_ratio = self.csa_ratios[self.settings.csa_method]
        else:
            self.csa_ratio = self.section.area() / self.csa0
        if self.regional is not None:
            self.section_ratios = self.regional.ratios()

    def _solve(self) -> int:
        """Newton from the previous state; a failure with a lagged Jacobian is retried
        once with a fresh one before the caller cuts the step. Kept factors retry
        inside their own solve."""
        if self.settings.newton == "kept":
            amount = self.comm.allreduce(float(np.sum(self.growth.cell_det())), op=MPI.SUM)
            amount = math.log(amount / self.comm.allreduce(len(self.growth.cells), op=MPI.SUM))
            with self.monitor.track("mechanics"):
                return self.jacobian.solve(amount)
        try:
            with self.monitor.track("mechanics"):
                return self.problem.solve()
        except SolverError:
            if self.jacobian.lag == 1:
                raise
            self.jacobian.refresh()
            with self.monitor.track("mechanics"):
                return self.problem.solve()

    def _grow(self, theta, halvings: int = 0, fibre: float | None = None) -> tuple[int, int]:
        """Grow by ϑ (and ϑ_f along the fibres, where given) and solve; on a failed solve,
        retry as two half increments √ϑ (√ϑ_f)."""
        with self.monitor.track("growth update"):
            self.growth.grow(theta, fibre)
        try:
            iterations = self._solve()
        except SolverError:
            self.growth.revert()
            if halvings >= self.settings.max_halvings:
                raise
            root = np.sqrt(theta)
            half = None if fibre is None else math.sqrt(fibre)
            its1, h1 = self._grow(root, halvings + 1, half)
            its2, h2 = self._grow(root, halvings + 1, half)
            return its1 + its2, max(h1, h2)
        with self.monitor.track("growth update"):
            self.growth.accept()
        return iterations, halvings

    def _step(self, theta, t0: float, t1: float, fibre: float | None = None) -> tuple[int, int]:
        """One growth step; if it cannot be solved, the state before it comes back."""
        w, mult = self.problem.w.x.array.copy(), self.problem.multipliers.copy()
        Gbar = self.growth.Gbar  # replaced, never changed in place
        try:
            return self._grow(theta, fibre=fibre)
        except SolverError as err:
            self.problem.w.x.array[:] = w
            self.problem.multipliers = mult
            self.growth.set(Gbar)
            if self.settings.newton == "kept":
                self.jacobian.forget()
            raise GrowthFailure(
                f"growth step {self.step + 1} ({t0:g} h to {t1:g} h): Newton did not converge "
                f"with the step cut {self.settings.max_halvings} time(s): {err}",
                step=self.step + 1, t0=t0, t1=t1,
            ) from err

    def run(self) -> Iterator[StepReport]:
        """Yield the initial state (not after a resume), then one report per growth step
        to the protocol's end. Raises GrowthFailure with the state of the last step."""
        if not self.resumed:
            yield self._report(0)
        s = self.settings
        periods = self.protocol.periods()
        while self.period < len(periods):
            t0, t1, in_session = periods[self.period]
            # the session's stretch, where along-fibre growth responds to it (None: no fibre growth)
            stretch = (self.protocol.stretch_at(t0, t1) if in_session and s.fiber_growth == "stretch" else None)
            if self.period_states is None:
                times = growth.step_times(t0, t1, s.growth_dt)
                error = ys = None
                try:
                    with self.monitor.track("signaling"):
                        _, ys = self.integrator(
                            self.params, self.protocol, self.y, t0, t1, s.signaling_dt, out_times=times, kM=self.kM
                        )
                except SignalingError as err:
                    error = str(err)
                # per-cell ODEs may fail on some ranks only: every rank stops alike
                errors = [e for e in self.comm.allgather(error) if e is not None]
                if errors:
                    raise GrowthFailure(f"signaling from {t0:g} h to {t1:g} h: {errors[0]}",
                                        step=self.step + 1, t0=t0, t1=t1)
                self.period_times, self.period_states, self.period_step = times, ys, 0
                self.period_kM = self.kM
            times, ys = self.period_times, self.period_states
            while self.period_step + 1 < len(times):
                k = self.period_step + 1
                iterations = halvings = 0
                dN = growth.population_change(s.growth_increment, ys[k - 1], ys[k], times[k] - times[k - 1],
                                              self.params, self.period_kM)
                if in_session and not s.grow_during_sessions:
                    dN = np.zeros_like(dN)
                N1 = None
                if s.detraining is not None:  # the gain's turnover, added to the step's dN
                    N1 = growth.detrained(self.y[4], dN, times[k] - times[k - 1], s.detraining)
                    dN = N1 - self.y[4]
                theta = growth.area_multiplier(dN, self.csa_ratio)
                fibre = fiber_growth = None  # the step's along-fibre increment ϑ_f,k/ϑ_f,k-1, and ϑ_f,k
                if stretch is not None:
                    fiber_growth = growth.fibre_stretch_step(self.fiber_growth, stretch, times[k] - times[k - 1],
                                                             s.fiber_tau, s.fiber_crit)
                    fibre = fiber_growth / self.fiber_growth if fiber_growth != self.fiber_growth else None
                # f vanishes below the thresholds (the rest week, early recovery):
                # nothing grows, so the previous equilibrium stands.
                if fibre is not None or self.comm.allreduce(bool(np.any(theta != 1.0)), op=MPI.LOR):
                    iterations, halvings = self._step(theta, float(times[k - 1]), float(times[k]), fibre)
                    if fibre is not None:
                        self.fiber_growth = fiber_growth
                    with self.monitor.track("measures"):
                        self._measure_csa()
                        self.volume_ratio = self.problem.volume() / self.volume0
                    self.kM = self.kM0 * growth.feedback(self.csa_ratio, s.feedback)
                self.y = ys[k]
                if N1 is not None:  # the ODEs go on from the N the turnover left
                    self.y = ys[k].copy()
                    self.y[4] = N1
                self.t = float(times[k])
                self.step += 1
                self.period_step = k
                yield self._report(iterations, halvings)
            self.period += 1
            self.period_times = self.period_states = None

    # ------------------------------------------------------------------- checkpoints

    def state(self) -> State:
        """The whole state of the run after its last step, for a checkpoint (collective).

        The mixed solution is stored as each cell's own dof values in the element's
        order: that order follows the cell's vertices as the mesh file lists them, so it
        is the same on any partition (P2 has one dof per edge, so no dof transformation
        enters); so are the arrays of w's layout the jacobian keeps. Ḡ is per quadrature
        point of the cell (`growthfield.GrowthField.state`), whose points are placed by
        the same vertex order. Per-cell signaling parameters (random fields) are part of it.
        """
        problem, growth_field = self.problem, self.growth
        cells = growth_field.cells
        original = local_original_cells(self.geometry.mesh)[cells]
        wdofs = problem.W.dofmap.list[cells]
        per_cell = {"w": problem.w.x.array[wdofs], **growth_field.state()}
        jacobian = self.jacobian.state()
        glob = {
            "multipliers": np.asarray(problem.multipliers, dtype=float),
            "csa_ratio": self.csa_ratio,
            "volume_ratio": self.volume_ratio,
            "t": self.t,
            "step": self.step,
            "period": self.period,
            "period_step": self.period_step,
            "jacobian_count": jacobian["count"],
            "csa0": self.csa0,
            "volume0": self.volume0,
            **{name: value for name, value in zip(self.measures, self.csa_ratios.values())},
        }
        if self.section_ratios is not None:
            glob["csa_ratio_sections"] = self.section_ratios
        if self.settings.fiber_growth != "none":
            glob["fiber_growth"] = self.fiber_growth
        if jacobian["point"] is not None:
            w_j, g_j = jacobian["point"]
            per_cell["jacobian_w"] = w_j[wdofs]
            per_cell["jacobian_Gbar"] = growth_field.cell_rows(g_j)
        history = jacobian.get("history", [])  # the solutions kept for a predictor
        if history:
            glob["predictor_amounts"] = np.array([s for s, _, _ in history])
            glob["predictor_multipliers"] = np.array([m for _, _, m in history], dtype=float)
            per_cell["predictor_w"] = np.stack([w_k[wdofs] for _, w_k, _ in history], axis=1)
        arrays, multipliers = jacobian.get("secants", ([], None))
        if arrays:
            per_cell["secant_w"] = np.stack([a[wdofs] for a in arrays], axis=1)
            glob["secant_multipliers"] = multipliers
        per_cell_y = self.y.ndim == 2
        (per_cell if per_cell_y else glob)["y"] = self.y.T if per_cell_y else self.y
        if np.ndim(self.kM):
            per_cell["kM"] = np.asarray(self.kM)
        else:
            glob["kM"] = float(self.kM)
        if self.period_states is not None:
            glob["period_times"] = self.period_times
            if np.ndim(self.period_kM):
                per_cell["period_kM"] = np.asarray(self.period_kM)
            else:
                glob["period_kM"] = float(self.period_kM)
            ys = self.period_states
            if per_cell_y:
                per_cell["period_states"] = np.moveaxis(ys, 2, 0)  # (cell, time, species)
            else:
                glob["period_states"] = ys
        for f in dataclasses.fields(self.params):
            value = getattr(self.params, f.name)
            if isinstance(value, np.ndarray):
                per_cell[f"params.{f.name}"] = value
        return State(original, per_cell, glob)

    def restore(self, state) -> None:
        """Take over a `state` read back on this partition, perhaps another than the one
        that saved it: ``state.rows(name)`` gives a per-cell array for this rank's local
        cells, owned then ghost, or None where the state has no such array;
        ``state.glob`` the global values (`hyper.runs.checkpoint.Checkpoint`). The next
        `run` goes on from there."""
        rows, glob = state.rows, state.glob
        problem, growth_field = self.problem, self.growth
        nowned = len(growth_field.cells)
        mesh = self.geometry.mesh
        nlocal = nowned + mesh.topology.index_map(mesh.topology.dim).num_ghosts
        local = np.arange(nlocal, dtype=np.int32)
        wdofs = problem.W.dofmap.list[local]
        w = problem.w
        w.x.array[wdofs] = rows("w")
        w.x.scatter_forward()
        problem.multipliers = np.array(glob["multipliers"], dtype=float)
        growth_field.restore({"Gbar": rows("Gbar")})  # after w: the fibre directions come from it

        # per-cell parameters (random fields) come from the state: they are part of it
        names = [f"params.{f.name}" for f in dataclasses.fields(self.params)]
        params = {name.split(".", 1)[1]: rows(name)[:nowned] for name in names if rows(name) is not None}
        if params:
            self.params = dataclasses.replace(self.params, **params)
            self.kM0 = self.params.kM
        y = rows("y")
        self.y = np.ascontiguousarray(y[:nowned].T) if y is not None else np.array(glob["y"], dtype=float)
        kM = rows("kM")
        self.kM = np.array(kM[:nowned]) if kM is not None else float(glob["kM"])
        self.csa_ratio = float(glob["csa_ratio"])
        if self.settings.fiber_growth != "none":
            self.fiber_growth = float(glob["fiber_growth"])  # the digest names the switch: a state of it has ϑ_f
        self.volume_ratio = float(glob["volume_ratio"])
        # a checkpoint from before both CSA measures were kept has neither: unknown until measured
        self.csa_ratios = {method: float(glob[name]) if name in glob else float("nan")
                           for method, name in zip(self.csa_ratios, self.measures)}
        if self.section_ratios is not None:
            # a checkpoint from before the regional sections were kept has none: unknown until measured
            self.section_ratios = (np.array(glob["csa_ratio_sections"], dtype=float) if "csa_ratio_sections" in glob
                                   else np.full(len(self.section_ratios), np.nan))
        self.t = float(glob["t"])
        self.step = int(glob["step"])
        self.period = int(glob["period"])
        self.period_step = int(glob["period_step"])
        if "period_times" in glob:
            self.period_times = np.array(glob["period_times"], dtype=float)
            ys = rows("period_states")
            self.period_states = (np.ascontiguousarray(np.moveaxis(ys[:nowned], 0, 2)) if ys is not None
                                  else np.array(glob["period_states"], dtype=float))
            kM = rows("period_kM")
            if kM is not None:
                self.period_kM = np.array(kM[:nowned])
            else:  # uniform; or a checkpoint from before it was kept (only the left-point increment reads it)
                self.period_kM = float(glob["period_kM"]) if "period_kM" in glob else self.kM
        else:
            self.period_times = self.period_states = None

        def w_array(values) -> np.ndarray:
            out = np.zeros_like(w.x.array)
            out[wdofs] = values
            return out

        jw = rows("jacobian_w")
        point = None if jw is None else (w_array(jw), growth_field.from_cell_rows(rows("jacobian_Gbar")))
        jacobian = {"count": int(glob["jacobian_count"]), "point": point}
        kept = rows("predictor_w")
        if kept is not None:
            jacobian["history"] = [
                (float(amount), w_array(kept[:, i]), np.array(glob["predictor_multipliers"][i], dtype=float))
                for i, amount in enumerate(np.asarray(glob["predictor_amounts"], dtype=float))
            ]
        pairs = rows("secant_w")
        if pairs is not None:
            jacobian["secants"] = ([w_array(pairs[:, i]) for i in range(pairs.shape[1])],
                                   np.asarray(glob["secant_multipliers"], dtype=float))
        self.jacobian.restore(jacobian)
        self.resumed = True


MECHANICS_PREFIX = "mechanics_"


def jacobian_lag(value) -> int:
    """The Newton matrix refresh interval from an option value (InputError if invalid)."""
    try:
        lag = int(value)
    except (TypeError, ValueError):
        lag = 0
    if lag < 1 and lag not in (-1, -2):
        raise InputError(f"{LAG_OPTION} must be a positive integer (or -1: never refresh), got {value!r}")
    return lag


@contextlib.contextmanager
def _taken_from_database(name: str):
    """Yield the value of a PETSc option (None if unset), absent from the database
    meanwhile so that PETSc's own setting of that name stays at its default."""
    db = PETSc.Options()
    value = db.getString(name) if db.hasName(name) else None
    if value is not None:
        db.delValue(name)
    try:
        yield value
    finally:
        if value is not None:
            db.setValue(name, value)


def build_model(
    geometry,
    a0,
    protocol: Protocol,
    *,
    params: signaling.SignalingParams | None = None,
    material=None,
    settings: GrowthSettings = GrowthSettings(),
    petsc_options: dict | None = None,
    linear_solver: str = "lu",
    integrator: Callable | None = None,
    monitor=None,
    normalize_fibres: bool = True,
) -> CoupledModel:
    """The `CoupledModel` of a geometry with fibres ``a0``, with its default parts: a
    `growthfield.GrowthField` as ``settings`` place it, the `MechanicsProblem` of
    ``material`` (default: its own) with ``petsc_options`` (snes_lag_jacobian, here or
    as -mechanics_snes_lag_jacobian, goes to a `LaggedJacobian` and never reaches PETSc),
    ``linear_solver`` and ``normalize_fibres``, the Newton solver ``settings.newton``
    names, and the section of the mesh (its tagged facets, else a `PlaneSection`); with
    ``settings.stimulus`` "local", the stimulus factors of the contraction at each session
    intensity of the protocol (`stimulus.session_factors`).
    ``monitor`` (default `NoTiming`) times the model and its Newton solver."""
    monitor = monitor if monitor is not None else NoTiming()
    growth_field = growthfield.GrowthField(geometry.mesh, a0, geometry.quadrature_degree, settings.growth_fields)
    kwargs = {} if material is None else {"material": material}
    options = dict(petsc_options or {})
    lag = jacobian_lag(options.pop(LAG_OPTION, JACOBIAN_LAG))
    with _taken_from_database(MECHANICS_PREFIX + LAG_OPTION) as value:
        if value is not None:
            lag = jacobian_lag(value)
        problem = MechanicsProblem(
            geometry,
            a0,
            growth=growth_field.function,
            consistent_stress=settings.consistent_stress,
            petsc_options=options,
            options_prefix=MECHANICS_PREFIX,
            linear_solver=linear_solver,
            normalize_fibres=normalize_fibres,
            **kwargs,
        )
    growth_field.set_deformation(problem.F)
    if settings.newton == "kept":
        jacobian = KeptFactors(problem, growth_field.function, monitor)
    else:
        jacobian = LaggedJacobian(problem, growth_field.function, lag, monitor)
    if geometry.midsection is not None:
        section_ = growthfield.FacetSection(geometry, problem.F)
    else:
        section_ = PlaneSection(problem)
    regional = (RegionalSections(problem, section.section_fractions(settings.sections)) if settings.sections
                else None)
    factors, record = None, {}
    if settings.stimulus == "local":
        factors, record = stimulus.session_factors(geometry, a0, protocol.intensities.tolist(),
                                                   normalize_fibres=normalize_fibres, petsc_options=options,
                                                   linear_solver=linear_solver, **kwargs)
    return CoupledModel(problem, growth_field, section_, jacobian, protocol, params=params, settings=settings,
                        integrator=integrator, monitor=monitor, regional=regional, stimulus_factors=factors,
                        stimulus_record=record)
