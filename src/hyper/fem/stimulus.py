"""Local mechanosensing (issue 35 item 2, `--stimulus local`): the exercise stimulus of
each cell from the active fibre stress of the session's contraction.

The paper drives every cell with one stimulus a1 = β I Fmax during a session. Here cell c
gets β s_c I Fmax, where s_c is the active fibre Cauchy stress of the contraction at
activation α = I, a·σ_act a = α σact fact(λ/λ0) / J (a = F a0 / |F a0|, MODEL.md §3),
averaged over the cell and divided by its volume-weighted mean over the muscle
(`normalised`): the mean factor is 1, so the muscle as a whole receives the paper's
stimulus, and a uniform stress gives every cell exactly 1, the paper's model.

The contraction is solved once, on the reference body before any growth, by a
`MechanicsProblem` of its own (the model's own Newton state is left alone), with α raised
by `ramp` through the protocol's session intensities, one factor field each
(`session_factors`); with several, `SessionFactors` gives each session its intensity's.
docs/local-mechanosensing.md says why once.
"""

from __future__ import annotations

import dataclasses

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem.mechanics import MechanicsProblem, SolverError
from hyper.model import material as mat
from hyper.model.failure import GrowthFailure

STIMULI = ("global", "local")
# Steps of the activation ramp to the session's intensity, each halved on a failed Newton
# solve up to RAMP_HALVINGS times, those before the last stopped at LOOSE_RTOL. To 0.8 on
# BFLH_VHF_Left (measured by hand, the Newton iterations of the solves that converged and the
# CPU time): 8 steps at 1e-3, 41 and 58 s; 4 steps at the solver's 1e-8, 51 and 76 s; 4 or 2
# steps at 1e-4, 46 and 69 or 78 s; the factors agree to 2e-8.
RAMP_STEPS = 8
RAMP_HALVINGS = 6
LOOSE_RTOL = 1e-3


def active_fibre_stress(problem: MechanicsProblem):
    """a·σ_act a = α σact fact(λ/λ0) / J of ``problem``'s law (Pa), as UFL; of the elastic part
    Fe of a grown body (the law sees Fe: σ = Je⁻¹ Fe S Feᵀ)."""
    m = problem.material
    ell = mat.fibre_stretch(problem.Fe, problem.a0) / m.lambda0
    return problem.alpha * m.sigma_act * mat.f_act(ell) / ufl.det(problem.Fe)


class CellAverages:
    """The mean over each owned cell of a UFL expression, and the cells' volumes, by the
    mesh's quadrature: ∫_c e dx / |c|, in the order of the owned cells (local index)."""

    def __init__(self, geometry, expression):
        mesh = geometry.mesh
        dg0 = fem.functionspace(mesh, ("DG", 0))
        v = ufl.TestFunction(dg0)
        ncells = mesh.topology.index_map(mesh.topology.dim).size_local
        self._dofs = dg0.dofmap.list[np.arange(ncells, dtype=np.int32)][:, 0]
        self._form = fem.form(expression * v * geometry.dx)
        self.volumes = self._assemble(fem.form(v * geometry.dx))

    def _assemble(self, form) -> np.ndarray:
        vec = fem.assemble_vector(form)
        return vec.array[self._dofs].copy()  # a DG0 dof belongs to its cell: no ghost adds to it

    def __call__(self) -> np.ndarray:
        return self._assemble(self._form) / self.volumes


def normalised(values: np.ndarray, volumes: np.ndarray, comm) -> np.ndarray:
    """``values`` (this rank's cells) divided by their volume-weighted mean over all ranks.

    The mean is taken about the largest value m, m + Σ (v_c - m) |c| / Σ |c|: a uniform field
    gives m exactly, hence factors of exactly 1 (the plain Σ v_c |c| / Σ |c| is off by an ulp
    or two), and on any partition the same mean up to the order of the sum. Collective.
    A field that vanishes everywhere (no activation) gives ones: no cell is singled out."""
    values = np.asarray(values, dtype=float)
    volumes = np.asarray(volumes, dtype=float)
    top = comm.allreduce(float(np.max(values, initial=-np.inf)), op=MPI.MAX)
    shift = comm.allreduce(float(np.sum((values - top) * volumes)), op=MPI.SUM)
    total = comm.allreduce(float(np.sum(volumes)), op=MPI.SUM)
    mean = top + shift / total
    if not np.isfinite(mean) or comm.allreduce(bool(np.any(values < 0)), op=MPI.LOR):
        raise InputError(f"the stimulus field must be finite and >= 0 (mean {mean:g})")
    if mean <= 0.0:
        return np.ones_like(values)
    return values / mean


def ramp(problem: MechanicsProblem, target: float, steps: int = RAMP_STEPS,
         halvings: int = RAMP_HALVINGS, loose: float | None = LOOSE_RTOL) -> int:
    """Raise α from its value to ``target`` in ``steps`` equal steps, each halved on a failed
    solve; the Newton iterations taken. The steps before the last stop at the relative
    tolerance ``loose`` (None: the solver's own): they only bring Newton near the last one,
    which stops at the solver's. Raises SolverError after ``halvings`` cuts."""

    def advance(a: float, b: float, left: int) -> int:
        problem.alpha.value = b
        try:
            return problem.solve()
        except SolverError:
            problem.alpha.value = a
            if left == 0:
                raise
        middle = 0.5 * (a + b)
        return advance(a, middle, left - 1) + advance(middle, b, left - 1)

    start = float(problem.alpha.value)
    levels = np.linspace(start, target, steps + 1)
    rtol = problem.snes.getTolerances()[0]
    iterations = 0
    try:
        for k, (a, b) in enumerate(zip(levels[:-1], levels[1:])):
            last = k == steps - 1
            problem.snes.setTolerances(rtol=rtol if last or loose is None else max(rtol, loose))
            iterations += advance(float(a), float(b), halvings)
    finally:
        problem.snes.setTolerances(rtol=rtol)
    return iterations


def session_factors(geometry, a0, intensities, *, material=None, normalize_fibres: bool = True,
                    petsc_options: dict | None = None, linear_solver: str = "lu",
                    growth=None) -> tuple[dict[float, np.ndarray], dict]:
    """The stimulus factor s_c of each owned cell (module docstring) for sessions of each of
    the ``intensities`` (none, or 0: no activation, all ones), by one ramp through them in
    increasing order; and a record of the contraction: the activation, its Newton iterations,
    the range and the volume-weighted mean of the stress (Pa), each a number for one
    intensity and a list (in increasing order) for several. GrowthFailure where the
    contraction cannot be solved. ``growth``: a total growth tensor Ḡ to contract the grown
    body with (a run's `GrowthField.function`; None: the reference body, what a run uses).
    Collective."""
    kwargs = {} if material is None else {"material": material}
    if growth is not None:
        kwargs["growth"] = growth
    problem = MechanicsProblem(geometry, a0, options_prefix="stimulus_", normalize_fibres=normalize_fibres,
                               petsc_options=petsc_options, linear_solver=linear_solver, **kwargs)
    averages = CellAverages(geometry, active_fibre_stress(problem))
    comm = geometry.mesh.comm
    total = comm.allreduce(float(np.sum(averages.volumes)), op=MPI.SUM)
    factors, rows = {}, []
    for alpha in sorted({float(i) for i in intensities if i}) or [0.0]:
        try:
            iterations = ramp(problem, alpha) if alpha > 0.0 else 0
        except SolverError as err:  # before the first growth step: the run fails as a step would
            problem.snes.destroy()
            raise GrowthFailure(f"the contraction of --stimulus local at α = {alpha:g}: {err}", step=1, t0=0.0,
                                t1=0.0) from err
        stress = averages()
        factors[alpha] = normalised(stress, averages.volumes, comm)
        rows.append({
            "stimulus_alpha": alpha,
            "stimulus_newton_iterations": iterations,
            "stimulus_stress_mean_pa": comm.allreduce(float(np.sum(stress * averages.volumes)), op=MPI.SUM) / total,
            "stimulus_stress_min_pa": comm.allreduce(float(np.min(stress, initial=np.inf)), op=MPI.MIN),
            "stimulus_stress_max_pa": comm.allreduce(float(np.max(stress, initial=-np.inf)), op=MPI.MAX),
            "stimulus_factor_min": comm.allreduce(float(np.min(factors[alpha], initial=np.inf)), op=MPI.MIN),
            "stimulus_factor_max": comm.allreduce(float(np.max(factors[alpha], initial=-np.inf)), op=MPI.MAX),
        })
    problem.snes.destroy()
    record = rows[0] if len(rows) == 1 else {name: [row[name] for row in rows] for name in rows[0]}
    return factors, record


def local_factors(geometry, a0, intensity: float | None, **kwargs) -> tuple[np.ndarray, dict]:
    """`session_factors` of one ``intensity`` (None: no activation): its factors and record."""
    factors, record = session_factors(geometry, a0, [] if intensity is None else [intensity], **kwargs)
    return next(iter(factors.values())), record


class SessionFactors:
    """A signaling integrator (the signature of `hyper.model.signaling.integrate`) whose
    members see, while a session drives the delayed stimulus a1(t − τd), β times the factor
    of that session's intensity: ``factors`` maps each intensity to one factor per member,
    ``beta`` is β before any factor. [t0, t1] is integrated in pieces cut where the driving
    session changes (at s_i + τd and e_i + τd); those are switch times, where RK4 cuts its
    steps anyway, so a piecewise integration is the single one's bits. Between sessions any
    β will do (a1 = a10), and intensity 0 needs no factor: the parameters' own β then."""

    def __init__(self, integrator, beta, factors: dict[float, np.ndarray]):
        self.integrator = integrator
        self.beta = beta
        self.factors = factors

    def __call__(self, params, protocol, y0, t0, t1, dt=0.05, *, out_times=None, kM=None):
        if np.ndim(params.tau_d):
            raise InputError("--stimulus local with several intensities needs one stimulus delay tau_d for all cells")
        tau_d = float(params.tau_d)
        starts, ends, intensities = protocol.starts, protocol.ends, protocol.intensities
        cuts = np.unique(np.concatenate([starts + tau_d, ends + tau_d]))
        bounds = [float(t0), *cuts[(cuts > t0) & (cuts < t1)].tolist(), float(t1)]
        times = np.array([t0, t1] if out_times is None else out_times, dtype=float)
        states = None
        y = y0
        for a, b in zip(bounds[:-1], bounds[1:]):
            mid = 0.5 * (a + b) - tau_d
            i = int(np.searchsorted(starts, mid, side="right")) - 1
            intensity = float(intensities[i]) if i >= 0 and mid < ends[i] else None
            p = params
            if intensity in self.factors:
                p = dataclasses.replace(params, beta=self.beta * self.factors[intensity])
            inside = (times >= a) & (times <= b) if a == t0 else (times > a) & (times <= b)
            wanted = np.unique(np.concatenate([[a], times[inside], [b]]))
            _, ys = self.integrator(p, protocol, y, a, b, dt, out_times=wanted, kM=kM)
            if states is None:
                states = np.empty((len(times), *ys.shape[1:]))
            states[inside] = ys[np.searchsorted(wanted, times[inside])]
            y = ys[-1]
        return times, states
