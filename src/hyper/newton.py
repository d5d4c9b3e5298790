"""Newton solves of growth steps with factors kept across steps (Anderson-accelerated).

A growth step changes the equilibrium by a fraction of a percent, so the LU factors of
a Newton matrix assembled a few steps earlier are still a good approximate inverse M⁻¹
of the current Jacobian. `KeptFactors` iterates on the equilibrium R(x) = 0 with them:

    f_i = -M⁻¹ R(x_i),   x_{k+1} = Σ α_i (x_i + f_i),   Σ α_i = 1,

where the α minimise |Σ α_i R(x_i)| over the last `DEPTH` + 1 iterates (Anderson
acceleration, in the norm of the residual that the convergence test measures). On a
linear problem this is GMRES right-preconditioned by M, so the few directions in which
an old matrix is badly wrong (soft rigid-like motions of the anatomical meshes, whose
stiffness changes with the growth: there the plain iteration x + f diverges) cost an
iteration or two instead of a new factorisation. An iteration is one residual assembly
and one back-substitution; the matrix is assembled and factorised again only when
`KEPT_ITERATIONS` iterations with factors of earlier steps did not converge (or the
residual grew), at the step's first iterate.

The first iterate is extrapolated from the last solutions (`ORDER`): the growth changes
the state smoothly, so on BFLH_VHF_Left (mwf) the first residual falls from 1e-2 (the
previous solution) to 1e-5. Measured in ``python -m hyper.bench speed``: 47 solved steps
of BFLH_VHF_Left take 5 factorisations and 145 iterations, against 39 and 154 of the
lagged SNES Newton, with the CSA/V series within 2e-7 of the growth.

The stopping test is SNES's, with its tolerances (snes_atol, snes_rtol, snes_max_it
and snes_divergence_tolerance of the mechanics solver's options), so that a step ends
as converged as a SNES Newton solve would.

State kept across solves, all in the checkpoint: the point (w, Ḡ) where the matrix was
assembled, so that a resumed run assembles the same matrix (`rebuild`); the solutions
the predictor extrapolates (`history`); the iteration count (`count`). So a resumed run
continues bit for bit. The Anderson history is per solve.
"""

from __future__ import annotations

import contextlib
import math

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np

from hyper.mechanics import SolverError

DEPTH = 5  # earlier iterates combined in each Anderson step
# The first iterate extrapolates the last ORDER + 1 solutions, as polynomials in the growth
# amount (log of the mean det Ḡ): on BFLH_VHF_Left (mwf) the first residual falls from
# 1e-2 to 1e-5, and the soft motions start within the reach of kept factors.
ORDER = 2
# Iterations tried with the factors of an earlier step before the matrix is assembled anew.
KEPT_ITERATIONS = 6
RCOND = 1e-12  # of the scaled least-squares problem: nearly dependent residuals are dropped


class _NoTiming:
    def track(self, name):
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
        self.monitor = monitor if monitor is not None else _NoTiming()
        self.depth = depth
        self.count = 0  # iterations over all solves
        self.assemblies = 0  # Newton matrices assembled (each factorised once)
        self.point: tuple[np.ndarray, np.ndarray] | None = None  # (w, Ḡ) local arrays of the last assembly
        # the last solutions: (growth amount, w local array, multipliers), oldest first
        self.history: list[tuple[float, np.ndarray, np.ndarray]] = []
        K = problem.jacobian_matrix
        ksp = problem.snes.getKSP()
        ksp.setOperators(K, K)
        self.pc = ksp.getPC()
        self.x = problem.solution_vector
        self._r = K.createVecLeft()

    def _assemble(self, x) -> None:
        problem = self.problem
        with self.monitor.track("jacobian assembly"):
            problem.assemble_jacobian(x)
            self.point = (problem.w.x.array.copy(), self.growth_function.x.array.copy())
        self.assemblies += 1

    def _factorise(self) -> None:
        # PETSc factorises only a matrix whose state changed since the last set-up
        with self.monitor.track("factorisation"):
            self.pc.setUp()

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
            self.pc.apply(r, f)
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
            problem.w.x.array[:] = previous[0]
            problem.w.x.scatter_forward()
            problem.multipliers = previous[1]
            raise
        self.history.append((amount, problem.w.x.array.copy(), problem.multipliers.copy()))
        del self.history[: -(ORDER + 1)]
        return iterations

    def forget(self) -> None:
        """Drop the solutions kept for the predictor (the state went back before them)."""
        self.history.clear()

    def _predict(self, amount: float) -> None:
        """w and μ extrapolated to ``amount`` through the kept solutions (Lagrange)."""
        points = self.history
        if len(points) < 2 or len({s for s, _, _ in points} | {amount}) < len(points) + 1:
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
        history: list[tuple] = []  # (x_i + f_i, R_i)
        iterations = kept = 0
        while True:
            self._factorise()
            f = x.duplicate()
            self._correction(r, f)
            f.axpy(1.0, x)  # the plain iterate x + f
            history.append((f, r.copy()))
            del history[: -(self.depth + 1)]
            self._combine(history, x)
            norm = self._residual(x, r)
            iterations += 1
            self.count += 1
            if not math.isfinite(norm):
                reason = "DIVERGED_FNORM_NAN"
            elif norm <= tol:
                return iterations
            elif iterations >= max_it:
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
            history.clear()
            fresh = True

    def _combine(self, history: list[tuple], x) -> None:
        """x = Σ α_i g_i with the α (Σ α = 1) that minimise |Σ α_i R_i| (history of (g, R))."""
        g_k, r_k = history[-1]
        if len(history) == 1:
            g_k.copy(x)
            return
        diffs = []
        for _, r_j in history[:-1]:
            d = r_j.copy()
            d.axpy(-1.0, r_k)
            diffs.append(d)
        m = len(diffs)
        gram = np.empty((m, m))
        rhs = np.empty(m)
        for i in range(m):
            rhs[i] = -diffs[i].dot(r_k)
            for j in range(i, m):
                gram[i, j] = gram[j, i] = diffs[i].dot(diffs[j])
        scale = np.sqrt(np.maximum(np.diag(gram), np.finfo(float).tiny))
        gamma = np.linalg.lstsq(gram / np.outer(scale, scale), rhs / scale, rcond=RCOND)[0] / scale
        g_k.copy(x)
        for (g_j, _), c in zip(history[:-1], gamma):
            x.axpy(c, g_j)
            x.axpy(-c, g_k)

    def _message(self, iterations: int, reason: str) -> str:
        return (f"Newton did not converge after {iterations} iterations with kept factors ({reason}); "
                "previous solution restored")
