"""Newton solves of growth steps with factors kept across steps, and secants kept too.

A growth step changes the equilibrium by a fraction of a percent, so the LU factors of
a Newton matrix assembled a few steps earlier are still a good approximate inverse M⁻¹
of the current Jacobian J. `KeptFactors` iterates on the equilibrium R(x) = 0 with them,
corrected by the secant pairs (s_i, y_i) = (Δx_i, ΔR_i) of the last `DEPTH` iterations
(of this solve and of earlier ones): the multisecant inverse

    H = M⁻¹ + (S − M⁻¹Y)(YᵀY)⁻¹Yᵀ,    x_{k+1} = x_k − H R(x_k),

satisfies H y_i = s_i, so it is right wherever an earlier iteration has probed J, and
costs one back-substitution of the part of R outside the span of Y. With the pairs of
this solve only, this is Anderson acceleration (type II), on a linear problem GMRES
right-preconditioned by M. The directions in which an old matrix is badly wrong are few
(soft rigid-like motions of the anatomical meshes, whose stiffness changes with the
growth: there the plain iteration x − M⁻¹R diverges) and the same from step to step, so
pairs carried over from the earlier steps correct them from a step's first iteration.
A pair stays a good secant of J as long as J changes little; they are dropped when the
matrix is assembled anew. An iteration is one residual assembly and one back-substitution;
the matrix is assembled and factorised again only when `KEPT_ITERATIONS` iterations with
factors of earlier steps did not converge (or the residual grew), at the step's first
iterate.

The first iterate is extrapolated from the last solutions (`ORDER`), as polynomials in
the growth amount through nodes at least `SPACING` times the extrapolation's reach apart:
protocols alternate long and short periods, and a quadratic through two solutions a short
period apart amplifies their errors (left at the tolerance) by the square of the ratio.

Measured in ``python -m hyper.bench speed`` (47 solved steps of BFLH_VHF_Left, mwf):
see the README's speed section for the numbers of this and the earlier solvers.

The stopping test is SNES's, with its tolerances (snes_atol, snes_rtol, snes_max_it
and snes_divergence_tolerance of the mechanics solver's options), so that a step ends
as converged as a SNES Newton solve would.

State kept across solves, all in the checkpoint (`KeptFactors.state`): the point (w, Ḡ)
where the matrix was assembled, so that a resumed run assembles the same matrix
(`rebuild`); the solutions the predictor extrapolates (`history`); the secant pairs
(`secants`); the iteration count (`count`). So a resumed run continues bit for bit.

`LaggedJacobian` is the other way to solve a step: SNES's Newton with a matrix
reassembled every few iterations (before issue 17).
"""

from __future__ import annotations

import contextlib
import math

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper.fem.mechanics import SolverError, weak_callback

DEPTH = 10  # secant pairs kept, over this and earlier solves
# The first iterate extrapolates ORDER + 1 solutions, as polynomials in the growth amount
# (log of the mean det Ḡ): on BFLH_VHF_Left (mwf) the first residual falls from 1e-2 (the
# previous solution) to 1e-6..1e-5, and the soft motions start within reach of kept factors.
ORDER = 2
KEPT_SOLUTIONS = 6  # the latest solutions, from which the nodes are chosen
SPACING = 0.5  # least distance of the nodes, as a fraction of the extrapolation's reach
# Iterations tried with the factors of an earlier step before the matrix is assembled anew.
KEPT_ITERATIONS = 10
RCOND = 1e-12  # of the scaled least-squares problem: nearly dependent residuals are dropped


class NoTiming:
    """The monitor a model has unless given one: it times nothing.

    A monitor is any object whose ``track(name)`` is a context manager around one
    phase of the work; `hyper.fem.coupled.CoupledModel` names its phases in `PHASES`.
    """

    def track(self, name: str) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext()


def assemble_jacobian_at(problem, growth_function, point: tuple[np.ndarray, np.ndarray], x) -> None:
    """Assemble the Jacobian again at a saved ``point`` (w and Ḡ), through the vector
    ``x``, and leave the problem's state (w, multipliers, Ḡ) as it was: how a resumed run
    gets back the Newton matrix it had kept."""
    saved = problem.w.x.array.copy(), problem.multipliers.copy(), growth_function.x.array.copy()
    growth_function.x.array[:] = point[1]
    n = problem.owned_size
    x.getArray()[:n] = point[0][:n]
    problem.assemble_jacobian(x)
    problem.w.x.array[:] = saved[0]
    problem.multipliers = saved[1]
    growth_function.x.array[:] = saved[2]


class KeptFactors:
    """The Newton matrix of a `MechanicsProblem`, assembled rarely, and the iteration
    that solves each growth step with its factors (module docstring).

    ``growth_function`` is the Ḡ the matrix depends on; ``monitor`` times "jacobian
    assembly", "factorisation", "back-solves" and "residual assembly".
    """

    def __init__(self, problem, growth_function, monitor=None, depth: int = DEPTH):
        self.problem = problem
        self.growth_function = growth_function
        self.monitor = monitor if monitor is not None else NoTiming()
        self.count = 0  # iterations over all solves
        self.assemblies = 0  # Newton matrices assembled (each factorised once)
        self.point: tuple[np.ndarray, np.ndarray] | None = None  # (w, Ḡ) local arrays of the last assembly
        # the last solutions: (growth amount, w local array, multipliers), oldest first
        self.history: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.x = problem.solution_vector
        self._r = problem.jacobian_matrix.createVecLeft()
        self.secants = Secants(problem.comm, depth)

    def _assemble(self, x) -> None:
        """A fresh matrix: secants of earlier ones would only spoil its exactness."""
        problem = self.problem
        with self.monitor.track("jacobian assembly"):
            problem.assemble_jacobian(x)
            self.point = (problem.w.x.array.copy(), self.growth_function.x.array.copy())
        self.assemblies += 1
        self.secants.clear()

    def _factorise(self) -> None:
        # PETSc factorises (or builds the multigrid) only where the matrix changed since
        with self.monitor.track("factorisation"):
            self.problem.setup_linear_solver()

    def rebuild(self, count: int, point: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Take over a saved state: the count and the matrix assembled at ``point``."""
        self.count = count
        self.point = point
        if point is not None:
            assemble_jacobian_at(self.problem, self.growth_function, point, self.x)

    def _residual(self, x, r) -> float:
        with self.monitor.track("residual assembly"):
            self.problem.assemble_residual(x, r)
        return r.norm()

    def _correction(self, r, f) -> None:
        with self.monitor.track("back-solves"):
            self.problem.apply_inverse(r, f)
        f.scale(-1.0)

    def solve(self, amount: float) -> int:
        """Solve for the current Ḡ, whose growth amount is ``amount``, from the solutions
        of earlier amounts (or the current state); returns the iterations.

        Raises SolverError (state restored) if the iteration fails even with fresh factors.
        """
        problem = self.problem
        previous = problem.w.x.array.copy(), problem.multipliers.copy()
        self._predict(amount)
        x = self.x
        problem.load_state(x)
        try:
            iterations = self._iterate(x)
        except SolverError:
            self.secants.clear()  # pairs of a diverging path: no secants of the solution's J
            problem.w.x.array[:] = previous[0]
            problem.w.x.scatter_forward()
            problem.multipliers = previous[1]
            raise
        self.history.append((amount, problem.w.x.array.copy(), problem.multipliers.copy()))
        del self.history[:-KEPT_SOLUTIONS]
        return iterations

    def secant_state(self) -> tuple[list[np.ndarray], np.ndarray]:
        """The secant pairs for a checkpoint: s_0, y_0, s_1, … as arrays of w's layout
        (ghosts filled), and their multiplier parts, one row each (all ranks)."""
        n = self.problem.owned_size
        scratch = self._scratch()
        arrays, multipliers = [], []
        for pair in zip(self.secants.s, self.secants.y):
            for v in pair:
                scratch.x.array[:n] = v[:n]
                scratch.x.scatter_forward()
                arrays.append(scratch.x.array.copy())
                multipliers.append(np.concatenate(self.problem.comm.allgather(v[n:])))
        width = len(self.problem.multipliers)
        return arrays, np.array(multipliers, dtype=float).reshape(len(arrays), width)

    def restore_secants(self, arrays: list[np.ndarray], multipliers: np.ndarray) -> None:
        """Take over pairs saved by `secant_state` (the Gram matrix is recomputed as it was built)."""
        n = self.problem.owned_size
        here = self.x.getLocalSize() - n  # the multipliers in this rank's unknowns (last rank)
        vectors = [np.concatenate([a[:n], m[len(m) - here:] if here else m[:0]]) for a, m in zip(arrays, multipliers)]
        self.secants.clear()
        for s, y in zip(vectors[0::2], vectors[1::2]):
            self.secants.add(s, y)

    def _scratch(self):
        return fem.Function(self.problem.W)

    def state(self) -> dict:
        """What the next solves need of the earlier ones, for a checkpoint (collective):
        ``count`` (iterations so far), ``point`` ((w, Ḡ) local arrays where the matrix
        was assembled, or None), ``history`` (the solutions kept for the predictor:
        (growth amount, w local array, multipliers), oldest first) and ``secants`` (the
        pairs as `secant_state` gives them)."""
        return {"count": self.count, "point": self.point, "history": self.history, "secants": self.secant_state()}

    def restore(self, state: dict) -> None:
        """Take over a `state` (w's arrays laid out for this partition): the matrix is
        assembled again at its point; ``history`` and ``secants``, where given, replace
        the solutions and pairs kept."""
        self.rebuild(int(state["count"]), state["point"])
        if state.get("history") is not None:
            self.history = list(state["history"])
        if state.get("secants") is not None:
            self.restore_secants(*state["secants"])

    def forget(self) -> None:
        """Drop the solutions kept for the predictor (the state went back before them)."""
        self.history.clear()
        self.secants.clear()

    def _predict(self, amount: float) -> None:
        """w and μ extrapolated to ``amount`` through kept solutions (Lagrange)."""
        points = self._nodes(amount)
        if len(points) < 2:
            return
        weights = []
        for i, (s_i, _, _) in enumerate(points):
            weight = 1.0
            for j, (s_j, _, _) in enumerate(points):
                if j != i:
                    weight *= (amount - s_j) / (s_i - s_j)
            weights.append(weight)
        problem = self.problem
        problem.w.x.array[:] = sum(c * w for c, (_, w, _) in zip(weights, points))
        problem.multipliers = sum(c * m for c, (_, _, m) in zip(weights, points))

    def _nodes(self, amount: float) -> list:
        if not self.history:
            return []
        nodes = [self.history[-1]]
        reach = abs(amount - nodes[0][0])
        for point in reversed(self.history[:-1]):
            if len(nodes) == ORDER + 1:
                break
            if abs(point[0] - nodes[-1][0]) >= SPACING * reach:
                nodes.append(point)
        if len(nodes) < min(ORDER + 1, len(self.history)):
            nodes = self.history[-(ORDER + 1):][::-1]
        return nodes if reach > 0 else []

    def _iterate(self, x) -> int:
        snes = self.problem.snes
        rtol, atol, _, max_it = snes.getTolerances()
        divergence = snes.getDivergenceTolerance()
        fresh = self.point is None  # factors assembled for this solve
        if fresh:
            self._assemble(x)
        r = self._r
        norm0 = norm = self._residual(x, r)
        if not math.isfinite(norm0):
            raise SolverError(self._message(0, "DIVERGED_FNORM_NAN"))
        if norm0 < atol:
            return 0
        tol = max(atol, rtol * norm0)
        start = x.copy()
        f = x.duplicate()
        iterations = kept = 0
        while True:
            self._factorise()
            r_old = r.getArray(readonly=True).copy()
            gamma = self.secants.coefficients(r_old)
            y_gamma, s_gamma = self.secants.combine(gamma)
            r.getArray()[:] = r_old - y_gamma
            self._correction(r, f)  # f = −M⁻¹(R − Yγ)
            step = f.getArray(readonly=True) - s_gamma
            x.getArray()[:] += step
            norm = self._residual(x, r)
            iterations += 1
            self.count += 1
            if not math.isfinite(norm):
                reason = "DIVERGED_FNORM_NAN"
            else:
                self.secants.add(step, r.getArray(readonly=True) - r_old)
                if norm <= tol:
                    return iterations
                if iterations >= max_it:
                    reason = "DIVERGED_MAX_IT"
                elif divergence > 0 and norm > divergence * norm0:
                    reason = "DIVERGED_DTOL"
                else:
                    reason = None
            kept += 1
            if reason is None and (fresh or (kept < KEPT_ITERATIONS and norm < norm0)):
                continue
            if fresh and reason is not None:
                raise SolverError(self._message(iterations, reason))
            # Slow (or failing) with factors of an earlier step: start again with the matrix
            # assembled at the start. Not at the best iterate: a small residual may hide a
            # large error in a soft motion, where a matrix would be a poor one.
            start.copy(x)
            self._assemble(x)
            norm = self._residual(x, r)
            fresh = True

    def _message(self, iterations: int, reason: str) -> str:
        return (f"Newton did not converge after {iterations} iterations with kept factors ({reason}); "
                "previous solution restored")


class LaggedJacobian:
    """The Newton matrix, reassembled every ``lag`` Newton iterations counted across
    solves (PETSc's snes_lag_jacobian with persistence), or when `refresh` asks.

    PETSc keeps that count inside the SNES where a restart cannot reach it. Here SNES
    asks at every iteration (its own lag is 1) and this object decides; an unchanged
    matrix keeps its LU factors, since PETSc refactors only a matrix whose state changed.
    The state is the count and the point (w and Ḡ) of the last assembly: `rebuild`
    assembles the same matrix again there.
    """

    def __init__(self, problem, growth_function, lag: int, monitor=None):
        self.problem = problem
        self.monitor = monitor if monitor is not None else NoTiming()
        self.growth_function = growth_function
        self.lag = lag if lag >= 1 else 0  # PETSc's -1/-2: never again after the first
        self.count = 0  # Newton iterations so far, over all solves
        self.assemblies = 0
        self.point: tuple[np.ndarray, np.ndarray] | None = None  # (w, Ḡ) local arrays
        self._refresh = False
        K = problem.jacobian_matrix
        problem.snes.setJacobian(weak_callback(self._jacobian), K, K)
        problem.snes.setFunction(weak_callback(self._residual), problem.snes.getFunction()[0])

    def _residual(self, snes, x, f) -> None:
        with self.monitor.track("residual assembly"):
            self.problem.assemble_residual(x, f)

    def refresh(self) -> None:
        """Assemble anew at the next Newton iteration."""
        self._refresh = True

    def _jacobian(self, snes, x, K, P) -> None:
        due = self.count == 0 or (self.lag > 0 and self.count % self.lag == 0)
        if due or self._refresh:
            with self.monitor.track("jacobian assembly"):
                self.problem.assemble_jacobian(x)
                self.point = (self.problem.w.x.array.copy(), self.growth_function.x.array.copy())
            self.assemblies += 1
            self._refresh = False
        self.count += 1

    def rebuild(self, count: int, point: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Take over a saved state: the count and the matrix assembled at ``point``."""
        self.count = count
        self.point = point
        if point is not None:
            assemble_jacobian_at(self.problem, self.growth_function, point, self.problem.solution_vector)

    def state(self) -> dict:
        """``count`` and ``point`` (as `KeptFactors.state`), for a checkpoint."""
        return {"count": self.count, "point": self.point}

    def restore(self, state: dict) -> None:
        """Take over a `state`: the count and the matrix at its point (the solutions and
        secants a `KeptFactors` state may have besides are not this solver's)."""
        self.rebuild(int(state["count"]), state["point"])


class Secants:
    """Secant pairs (s_i, y_i) = (Δx_i, ΔR_i), oldest first, as local arrays of the
    Newton unknowns, and their Gram matrix Y^T Y, kept across solves (module docstring)."""

    def __init__(self, comm, depth: int):
        self.comm = comm
        self.depth = depth
        self.clear()

    def clear(self) -> None:
        self.s: list[np.ndarray] = []
        self.y: list[np.ndarray] = []
        self.gram = np.empty((0, 0))

    def _dots(self, vectors, v) -> np.ndarray:
        return self.comm.allreduce(np.array([u @ v for u in vectors]), op=MPI.SUM)

    def coefficients(self, r: np.ndarray) -> np.ndarray:
        """The γ that minimise |r − Y γ| (scaled: the pairs' sizes differ by decades)."""
        if not self.y:
            return np.empty(0)
        rhs = self._dots(self.y, r)
        scale = np.sqrt(np.maximum(np.diag(self.gram), np.finfo(float).tiny))
        return np.linalg.lstsq(self.gram / np.outer(scale, scale), rhs / scale, rcond=RCOND)[0] / scale

    def combine(self, gamma: np.ndarray) -> tuple:
        """(Y γ, S γ), or zeros where there are no pairs."""
        return (sum(c * y for c, y in zip(gamma, self.y)), sum(c * s for c, s in zip(gamma, self.s)))

    def add(self, s: np.ndarray, y: np.ndarray) -> None:
        y = np.array(y)
        dots = self._dots(self.y + [y], y)
        m = len(self.y)
        gram = np.empty((m + 1, m + 1))
        gram[:m, :m] = self.gram
        gram[m, :] = gram[:, m] = dots
        self.s.append(np.array(s))
        self.y.append(y)
        self.gram = gram
        if len(self.y) > self.depth:
            del self.s[0], self.y[0]
            self.gram = self.gram[1:, 1:]
