"""IGF1–AKT–FOXO–mTOR signaling (MODEL.md §1): numpy kernels over a batch axis.

State ``y = (igf1, akt, foxo, mtor, N)``, shape (5,) for one member or (5, n) for a batch.
The batch axis is later the mesh cells of one rank or the samples of a Sobol analysis:
every parameter may be a float or an array of n per-member values.

- ``params``: `SignalingParams` (Table 2, units, validation) and TOML loading;
- ``model``: the rest state, the stimuli, the right-hand side and its switch times;
- ``integrators``: RK4 over the batch axis (numpy or compiled), the reference solution,
  the original code's RK45 (``METHODS``), the sampled series of a protocol;
- ``compiled``: the RK4 step in C, built at run time;
The Fig. 3A–E figure is `hyper.runs.signalingplot`; the command, `hyper.commands.signaling`.

The names below are the ones the rest of hyper uses.
"""

from hyper.model.protocols import PAPER
from hyper.model.signaling.integrators import (
    AUTO_MIN_MEMBERS,
    BACKENDS,
    CHUNK,
    FAILURES,
    METHODS,
    ORIGINAL_N0,
    SMALLEST_DT,
    SMALLEST_SAMPLE,
    SignalingError,
    c_backend_error,
    first_day,
    integrate,
    integrator,
    original,
    reference,
    run,
    start_state,
    step_count,
    stop_at_bounds,
)
from hyper.model.signaling.model import STATES, a1, a2, bump_duration, g, net_balance, rest_state, rhs, switch_times
from hyper.model.signaling.params import SignalingParams, load_params

__all__ = [
    "AUTO_MIN_MEMBERS", "BACKENDS", "CHUNK", "FAILURES", "METHODS", "ORIGINAL_N0",
    "SMALLEST_DT", "SMALLEST_SAMPLE", "PAPER", "STATES", "SignalingError", "SignalingParams",
    "a1", "a2", "bump_duration", "c_backend_error", "first_day", "g", "integrate", "integrator", "load_params",
    "net_balance", "original", "reference", "rest_state", "rhs", "run", "start_state", "step_count",
    "stop_at_bounds", "switch_times",
]
