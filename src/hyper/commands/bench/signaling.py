"""Signaling integrator benchmark: batch throughput, one run against SciPy's RK45, speed–accuracy.

python -m hyper.bench signaling [--quick] writes results/bench/signaling.json,
signaling_throughput.png and signaling_speed_accuracy.png. Run it in one process with
OMP_NUM_THREADS=1: the throughput is per core.

- Throughput in member-steps per second of ``integrate`` for 1e3, 1e4 and 1e5 members on
  the 9-week ``mwf`` protocol (a window of it for the larger batches), on both backends
  side by side (numpy batch and the compiled kernel, checked to give the same bits), next
  to a plain numpy RK4 with temporaries on the same window; and for batches of 1 to 64
  members (where ``backend="auto"`` starts to take C) on a 30-h window.
- One 9-week ``mwf`` run: ``integrate`` (dt = 0.05 h) against
  ``solve_ivp(method="RK45", max_step=0.05)`` of the same right-hand side (``rhs``), the
  way the paper integrated, with both errors of N(1512 h) against ``reference``.
- Speed–accuracy: error of N(1512 h) and wall time against dt, up to past RK4's stability
  limit; a step that blows up is recorded as a failure, not a number.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.model import signaling
from hyper.model.protocols import named
from hyper.model.signaling import compiled
from hyper.runs import plot

DTS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.55, 0.6, 0.65, 0.7, 0.8, 1.0)
QUICK_DTS = (0.02, 0.05, 0.1, 0.2, 0.4, 0.6, 0.7, 1.0)


def _best(fn, repeat: int) -> tuple[float, object]:
    best, value = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        value = fn()
        best = min(best, time.perf_counter() - start)
    return best, value


def _plain_rk4(params, protocol, y, t0, t1, dt):
    """The textbook numpy RK4 (new arrays for every operation) with uniform steps: the baseline."""
    p = params

    def f(t, y):
        x1, x2, x3, x4, n = y
        A1 = signaling.a1(t - p.tau_d, protocol, p)
        A2 = signaling.a2(t, protocol, p)
        growth = p.kM * np.maximum(x4 - p.thetaM, 0.0) - p.kF * np.maximum(x3 - p.thetaF, 0.0)
        return np.array([
            x1 * (A1 - p.b1 * x1),
            x2 * (A2 - p.b2 * x2 + p.c21 * x1),
            x3 * (p.a3 - p.b3 * x3 - p.c32 * x2),
            x4 * (p.a4 - p.b4 * x4 + p.c42 * x2 - p.c43 * x3),
            np.where((n >= p.Nmin) & (n <= p.Nmax), growth, 0.0),
        ])

    steps = int(round((t1 - t0) / dt))
    t = t0
    for _ in range(steps):
        k1 = f(t, y)
        k2 = f(t + dt / 2, y + dt / 2 * k1)
        k3 = f(t + dt / 2, y + dt / 2 * k2)
        k4 = f(t + dt, y + dt * k3)
        y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
    return steps, y


def _backends(n: int, t0: float, t1: float, repeat: int, c: bool) -> dict:
    """Both backends on one batch of n members, one after the other: walls, rates, same bits."""
    params, protocol, y0 = signaling.SignalingParams(), named("mwf"), signaling.rest_state()
    y = np.repeat(y0[:, None], n, axis=1) if n > 1 else y0
    steps = signaling.step_count(params, protocol, t0, t1)
    wall, (_, numpy_states) = _best(lambda: signaling.integrate(params, protocol, y, t0, t1, backend="numpy"), repeat)
    row = {"members": n, "t0": t0, "t1": t1, "steps": steps, "wall_s": wall, "member_steps_per_s": n * steps / wall}
    if c:
        wall_c, (_, c_states) = _best(lambda: signaling.integrate(params, protocol, y, t0, t1, backend="c"), repeat)
        row.update({"c_wall_s": wall_c, "c_member_steps_per_s": n * steps / wall_c,
                    "c_over_numpy": wall / wall_c, "c_identical": bool(np.array_equal(c_states, numpy_states))})
    return row


def _c_text(row: dict) -> str:
    if "c_wall_s" not in row:
        return ""
    same = "same bits" if row["c_identical"] else "DIFFERENT BITS"
    return f", C {row['c_member_steps_per_s']:.3g} (x{row['c_over_numpy']:.1f}, {same})"


def throughput(sizes, windows, repeat: int, c: bool) -> list[dict]:
    params, protocol, y0 = signaling.SignalingParams(), named("mwf"), signaling.rest_state()
    rows = []
    for n, (t0, t1) in zip(sizes, windows):
        y = np.repeat(y0[:, None], n, axis=1)
        row = _backends(n, t0, t1, repeat, c)
        # the baseline on a shorter window of the same stretch (it is slow)
        tp = t0 + min(t1 - t0, 24.0)
        wall_plain, (plain_steps, _) = _best(lambda: _plain_rk4(params, protocol, y, t0, tp, 0.05), 1)
        row["plain_numpy_member_steps_per_s"] = n * plain_steps / wall_plain
        row["speedup_over_plain_numpy"] = row["member_steps_per_s"] / row["plain_numpy_member_steps_per_s"]
        print(f"  {n:>7d} members: numpy {row['member_steps_per_s']:.3g} member-steps/s "
              f"(plain numpy RK4: {row['plain_numpy_member_steps_per_s']:.3g}, x{row['speedup_over_plain_numpy']:.2f})"
              + _c_text(row), flush=True)
        rows.append(row)
    return rows


def small_batches(sizes, window, repeat: int, c: bool) -> list[dict]:
    """Where the numpy batch's per-call overhead dominates: the case for AUTO_MIN_MEMBERS."""
    rows = []
    for n in sizes:
        row = _backends(n, *window, repeat, c)
        print(f"  {n:>7d} members: numpy {row['member_steps_per_s']:.3g} member-steps/s" + _c_text(row), flush=True)
        rows.append(row)
    return rows


def single_vs_rk45(reference_N: float, repeat: int) -> dict:
    from scipy.integrate import solve_ivp

    params, protocol, y0 = signaling.SignalingParams(), named("mwf"), signaling.rest_state()
    wall_rk4, (_, y) = _best(lambda: signaling.integrate(params, protocol, y0, 0.0, 1512.0, 0.05, backend="numpy"),
                             repeat)

    def fun(t, y):
        return signaling.rhs(t, y, params, protocol)

    wall_rk45, sol = _best(lambda: solve_ivp(fun, (0.0, 1512.0), y0, method="RK45", max_step=0.05), 1)
    calls = 2000
    wall_rhs, _ = _best(lambda: [fun(200.0, y0) for _ in range(calls)], 3)
    out = {
        "rk4_dt": 0.05,
        "rk4_steps": signaling.step_count(params, protocol, 0.0, 1512.0),
        "rk4_wall_s": wall_rk4,
        "rk4_rel_error_N": abs(y[-1, 4] / reference_N - 1),
        "rk45_wall_s": wall_rk45,
        "rk45_steps": int(sol.t.size - 1),
        "rk45_rhs_calls": int(sol.nfev),
        "rk45_rel_error_N": abs(sol.y[4, -1] / reference_N - 1),
        "rhs_call_s": wall_rhs / calls,
        "speed_ratio": wall_rk45 / wall_rk4,
    }
    # what RK45 would cost with a free right-hand side: a lower bound on the ratio
    out["rk45_wall_without_rhs_s"] = max(wall_rk45 - out["rk45_rhs_calls"] * out["rhs_call_s"], 0.0)
    out["speed_ratio_without_rhs"] = out["rk45_wall_without_rhs_s"] / wall_rk4
    print(f"  single mwf run: RK4 {wall_rk4:.3f} s (rel. error {out['rk4_rel_error_N']:.2e}), "
          f"RK45 {wall_rk45:.2f} s (rel. error {out['rk45_rel_error_N']:.2e}): x{out['speed_ratio']:.1f} "
          f"(x{out['speed_ratio_without_rhs']:.1f} even with a free RHS for RK45)", flush=True)
    return out


def speed_accuracy(dts, reference_N: float) -> list[dict]:
    params, protocol, y0 = signaling.SignalingParams(), named("mwf"), signaling.rest_state()
    rows = []
    for dt in dts:
        start = time.perf_counter()
        try:
            _, y = signaling.integrate(params, protocol, y0, 0.0, 1512.0, dt, backend="numpy")
        except signaling.SignalingError as err:
            rows.append({"dt": dt, "failed": True, "error": str(err), "wall_s": time.perf_counter() - start})
            print(f"  dt = {dt:5.2f} h: FAILED ({err})", flush=True)
            continue
        wall = time.perf_counter() - start
        rel = abs(y[-1, 4] / reference_N - 1)
        rows.append({"dt": dt, "failed": False, "rel_error_N": rel, "wall_s": wall,
                     "steps": signaling.step_count(params, protocol, 0.0, 1512.0, dt)})
        print(f"  dt = {dt:5.2f} h: rel. error of N(1512 h) {rel:.2e}, {wall:.3f} s", flush=True)
    return rows


def _charts(result: dict, folder: Path) -> list[Path]:
    plt = plot.pyplot()
    paths = []
    rows = result["throughput"]
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    n = np.array([r["members"] for r in rows], dtype=float)
    small = result["small_batches"]
    ns = np.array([r["members"] for r in small], dtype=float)
    ax.plot(n, [r["member_steps_per_s"] for r in rows], "o-", color="C0",
            label='integrate, backend="numpy" (chunked, in place)')
    ax.plot(ns, [r["member_steps_per_s"] for r in small], "o:", color="C0", mfc="none")
    if result["c_backend"] is None:
        ax.plot(n, [r["c_member_steps_per_s"] for r in rows], "^-", color="C2",
                label='integrate, backend="c" (compiled)')
        ax.plot(ns, [r["c_member_steps_per_s"] for r in small], "^:", color="C2", mfc="none")
        for r in rows:
            ax.annotate(f"x{r['c_over_numpy']:.1f}", (r["members"], r["c_member_steps_per_s"]), xytext=(0, 6),
                        textcoords="offset points", ha="center", fontsize=8, color="C2")
    ax.plot(n, [r["plain_numpy_member_steps_per_s"] for r in rows], "s--", color="C1",
            label="plain numpy RK4 (temporaries)")
    ax.axhline(1e7, color="k", ls=":", lw=1, label="goal 1e7")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(top=ax.get_ylim()[1] * 3)  # room for the ratios
    ax.set_xlabel("members in the batch")
    ax.set_ylabel("member-steps per second (one core)")
    load = result["machine"]["load_average_at_start"][0]
    ax.set_title(f"Batch RK4 throughput, mwf protocol (open: 30-h window; load {load:.1f} on "
                 f"{result['machine']['cpus']} cores)", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    paths.append(plot.save(fig, folder / "signaling_throughput.png", dpi=130))

    rows = result["speed_accuracy"]
    single = result["single_vs_rk45"]
    fig, (ea, ta) = plt.subplots(1, 2, figsize=(11, 4.2), constrained_layout=True)
    ok = [r for r in rows if not r["failed"]]
    bad = [r for r in rows if r["failed"]]
    dt = np.array([r["dt"] for r in ok])
    err = np.array([r["rel_error_N"] for r in ok])
    ea.loglog(dt, err, "o-", label="RK4, steps on switch times")
    guide = err[list(dt).index(0.05)] * (dt / 0.05) ** 4 if 0.05 in dt else None
    if guide is not None:
        ea.loglog(dt, guide, "k:", lw=1, label="slope 4")
    ea.loglog([0.05], [single["rk45_rel_error_N"]], "D", color="C2", label="SciPy RK45, max_step 0.05")
    top = max(err.max(), 1e-2) * 10
    for r in bad:
        ea.plot(r["dt"], top, "x", color="C3", ms=10, mew=2)
    if bad:
        ea.axvspan(min(r["dt"] for r in bad), max(r["dt"] for r in bad) * 1.05, color="C3", alpha=0.1,
                   label="fails: non-finite/negative state")
    ea.text(0.98, 0.02, "steps land on switch times: the 1-h sessions run at h = 1/ceil(1/dt),\n"
            "so dt in [0.5, 1) integrates them at h = 0.5 (the plateaus)", transform=ea.transAxes, fontsize=7,
            va="bottom", ha="right")
    ea.set_xlabel("dt (h)")
    ea.set_ylabel("relative error of N(1512 h)")
    ea.set_title("Accuracy against the DOP853 reference (mwf)")
    ea.grid(alpha=0.3, which="both")
    ea.legend(fontsize=8)
    ta.loglog(dt, [r["wall_s"] for r in ok], "o-", label="RK4, one member")
    ta.loglog([0.05], [single["rk45_wall_s"]], "D", color="C2", label="SciPy RK45, max_step 0.05")
    for r in bad:
        ta.plot(r["dt"], r["wall_s"], "x", color="C3", ms=10, mew=2)
    ta.set_xlabel("dt (h)")
    ta.set_ylabel("wall time (s)")
    ta.set_title("Cost of one 9-week run (×: time until SignalingError)")
    ta.grid(alpha=0.3, which="both")
    ta.legend(fontsize=8)
    paths.append(plot.save(fig, folder / "signaling_speed_accuracy.png", dpi=130))
    return paths


def parser() -> cli.Parser:
    p = cli.Parser("bench signaling", __doc__)
    p.add_argument("--quick", action="store_true", help="shorter windows and fewer dt values (about a minute)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:

    print("reference (DOP853, rtol 1e-13) ...", flush=True)
    params, protocol, y0 = signaling.SignalingParams(), named("mwf"), signaling.rest_state()
    start = time.perf_counter()
    reference_N = float(signaling.reference(params, protocol, y0, 0.0, 1512.0)[1][-1, 4])
    reference_s = time.perf_counter() - start
    sizes = (1_000, 10_000, 100_000)
    if args.quick:
        windows = ((168.0, 268.0), (168.0, 188.0), (168.0, 172.0))
    else:
        windows = ((0.0, 1512.0), (168.0, 468.0), (168.0, 198.0))
    c_backend = signaling.c_backend_error()  # builds or loads the kernel before any timing
    if c_backend is not None:
        print(f"no C backend, numpy only: {c_backend}", flush=True)
    print("throughput ...", flush=True)
    repeat = 1 if args.quick else 2
    result = {
        # other work on the machine slows every number; the ratios suffer least
        "machine": {**common.machine(), "python": platform.python_version(), "numpy": np.__version__,
                    "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")},
        "quick": args.quick,
        "chunk": signaling.CHUNK,
        "c_block": compiled.BLOCK,
        "c_flags": compiled.kernel_flags() if c_backend is None else None,
        "c_backend": c_backend,  # None: available; else why not
        "auto_min_members": signaling.AUTO_MIN_MEMBERS,
        "reference_N_1512": reference_N,
        "reference_wall_s": reference_s,
        "throughput": throughput(sizes, windows, repeat, c_backend is None),
    }
    print("small batches ...", flush=True)
    result["small_batches"] = small_batches((1, 2, 16, 64), (168.0, 198.0), repeat, c_backend is None)
    print("single run against RK45 ...", flush=True)
    result["single_vs_rk45"] = single_vs_rk45(reference_N, repeat=3)
    print("speed-accuracy ...", flush=True)
    result["speed_accuracy"] = speed_accuracy(QUICK_DTS if args.quick else DTS, reference_N)
    result["machine"]["load_average_at_end"] = os.getloadavg()
    failed = [r["dt"] for r in result["speed_accuracy"] if r["failed"]]
    stable = [r["dt"] for r in result["speed_accuracy"] if not r["failed"]]
    result["largest_stable_dt"] = max(stable) if stable else None
    result["smallest_failing_dt"] = min(failed) if failed else None

    folder = args.output
    path = folder / "signaling.json"
    io.write_json(path, result)
    charts = _charts(result, folder)
    print(f"wrote {path}, " + ", ".join(map(str, charts)))
    return 0


main = cli.entry(parser, run, world=False)
