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

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Iterator

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)

import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper import growth, section, signaling
from hyper.mechanics import MechanicsProblem, SolverError
from hyper.params import InputError
from hyper.protocols import Protocol


@dataclass(frozen=True)
class GrowthSettings:
    growth_dt: float = 24.0  # h, longest growth step; periods are cut into steps no longer
    signaling_dt: float = 0.05  # h, RK4 step of the signaling ODEs
    feedback: str = "hill"  # h(CSA/CSA0): hill, linear or none
    grow_during_sessions: bool = True  # False reproduces the original code
    consistent_stress: bool = True  # P = det(Fg) Fe S Fg⁻ᵀ; False: the original Fe S
    max_halvings: int = 4  # growth-step cuts tried before a failed solve stops the run

    def __post_init__(self):
        for name in ("growth_dt", "signaling_dt"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a finite positive number of hours, got {value!r}")
        if self.feedback not in growth.FEEDBACK_LAWS:
            raise InputError(
                f"feedback must be one of {', '.join(growth.FEEDBACK_LAWS)}, got {self.feedback!r}"
            )
        if not (isinstance(self.max_halvings, int) and self.max_halvings >= 0):
            raise InputError(f"max_halvings must be a non-negative integer, got {self.max_halvings!r}")


# Growth steps change the equilibrium by a fraction of a percent, so a Jacobian (and its
# LU factors) stays a good Newton matrix for many steps: refreshing it every 10
# iterations made the 9-week idealized run 4.8× faster with the same CSA to 1e-11.
GROWTH_PETSC_OPTIONS = {"snes_lag_jacobian": 10, "snes_lag_jacobian_persists": True}


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


def step_times(t0: float, t1: float, dt: float) -> np.ndarray:
    """[t0, …, t1] in equal steps no longer than dt (at least one step)."""
    n = max(1, math.ceil((t1 - t0) / dt - 1e-9))
    return np.linspace(t0, t1, n + 1)


class PlaneSection:
    """The mid-belly cross-section of a mesh without a tagged one (MODEL §4): the plane
    through the mean of all vertices, normal to their first principal axis, cut exactly
    through the tetrahedra; the deformed area is Nanson's integral on the cut."""

    def __init__(self, problem: MechanicsProblem):
        mesh = problem.geometry.mesh
        origin, normal = section.principal_plane(section.global_vertices(mesh, mesh.comm))
        self._cut = section.CutSection(mesh, origin, normal, degree=problem.geometry.quadrature_degree)
        # The cut evaluates ∇u from a plain vector function: keep a collapsed copy of u.
        self._w = problem.w
        self.u, self._map = problem.w.function_space.sub(0).collapse()
        self.u = fem.Function(self.u)
        self.area0 = self._cut.area0()

    def area(self) -> float:
        self.u.x.array[:] = self._w.x.array[self._map]
        return self._cut.deformed_area(self.u)


class CoupledModel:
    """Owns the mechanics problem, the growth field and the signaling state of one run."""

    def __init__(
        self,
        geometry,
        a0,
        protocol: Protocol,
        *,
        params: signaling.SignalingParams | None = None,
        material=None,
        settings: GrowthSettings = GrowthSettings(),
        petsc_options: dict | None = None,
    ):
        self.geometry = geometry
        self.comm = geometry.mesh.comm
        self.protocol = protocol
        self.params = params if params is not None else signaling.SignalingParams()
        self.settings = settings
        self.growth = growth.GrowthField(geometry.mesh, a0, geometry.quadrature_degree)
        kwargs = {} if material is None else {"material": material}
        self.problem = MechanicsProblem(
            geometry,
            a0,
            growth=self.growth.function,
            consistent_stress=settings.consistent_stress,
            petsc_options={**GROWTH_PETSC_OPTIONS, **(petsc_options or {})},
            **kwargs,
        )
        self.growth.set_deformation(self.problem.F)
        if geometry.midsection is not None:
            self.section = growth.FacetSection(geometry, self.problem.F)
        else:
            self.section = PlaneSection(self.problem)
        self.csa0 = self.section.area0
        self.volume0 = self.problem.volume()

        # Every run starts from the rest state of the baseline parameters (MODEL §1).
        # Per-cell parameters (one member per owned cell) give one ODE per cell, and ϑ,
        # G and Ḡ per cell; uniform parameters need one ODE for the whole body.
        rest = signaling.rest_state(signaling.SignalingParams())
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
        self.csa_ratio = 1.0
        self.volume_ratio = 1.0
        self.step = 0
        self.t = 0.0

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
        )

    def _solve(self) -> int:
        """Newton from the previous state; a failure with a lagged Jacobian is retried
        once with a fresh one before the caller cuts the step."""
        try:
            return self.problem.solve()
        except SolverError:
            snes = self.problem.snes
            lag = snes.getLagJacobian()
            if lag == 1:
                raise
            snes.setLagJacobian(-2)  # PETSc: recompute at the next iteration
            try:
                return self.problem.solve()
            finally:
                snes.setLagJacobian(lag)

    def _grow(self, theta, halvings: int = 0) -> tuple[int, int]:
        """Grow by ϑ and solve; on a failed solve, retry as two half increments √ϑ."""
        self.growth.grow(theta)
        try:
            iterations = self._solve()
        except SolverError:
            self.growth.revert()
            if halvings >= self.settings.max_halvings:
                raise
            root = np.sqrt(theta)
            its1, h1 = self._grow(root, halvings + 1)
            its2, h2 = self._grow(root, halvings + 1)
            return its1 + its2, max(h1, h2)
        self.growth.accept()
        return iterations, halvings

    def run(self) -> Iterator[StepReport]:
        """Yield the initial state, then one report per growth step to the protocol's end."""
        yield self._report(0)
        s = self.settings
        for t0, t1, in_session in self.protocol.periods():
            times = step_times(t0, t1, s.growth_dt)
            _, ys = signaling.integrate(
                self.params, self.protocol, self.y, t0, t1, s.signaling_dt, out_times=times, kM=self.kM
            )
            for k in range(1, len(times)):
                iterations = halvings = 0
                dN = ys[k][4] - ys[k - 1][4]
                if in_session and not s.grow_during_sessions:
                    dN = np.zeros_like(dN)
                theta = growth.area_multiplier(dN, self.csa_ratio)
                # f vanishes below the thresholds (the rest week, early recovery):
                # nothing grows, so the previous equilibrium stands.
                if self.comm.allreduce(bool(np.any(theta != 1.0)), op=MPI.LOR):
                    iterations, halvings = self._grow(theta)
                    self.csa_ratio = self.section.area() / self.csa0
                    self.volume_ratio = self.problem.volume() / self.volume0
                    self.kM = self.kM0 * growth.feedback(self.csa_ratio, s.feedback)
                self.y = ys[k]
                self.t = float(times[k])
                self.step += 1
                yield self._report(iterations, halvings)

    def settings_attributes(self) -> dict:
        return dataclasses.asdict(self.settings)
