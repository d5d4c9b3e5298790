"""The signaling model (MODEL.md §1): equilibrium, closed forms, RK4 order and accuracy against the
reference, batch == single bit for bit, the compiled backend == numpy bit for bit, the paper's
qualitative results, failures raised or masked, CLI, the batch split over MPI ranks, and ranks
building the compiled kernel at once."""

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from hyper.commands import signaling as signaling_job
from hyper.core.params import InputError
from hyper.model import signaling
from hyper.model.protocols import Protocol, Session, named
from hyper.model.signaling.model import lambert_w0

P0 = signaling.SignalingParams()
Y0 = signaling.rest_state()
END = 1512.0


@pytest.fixture(scope="module")
def mwf_reference():
    return signaling.reference(P0, named("mwf"), Y0, 0.0, END)[1][-1]


# --- parameters --------------------------------------------------------------------------


def test_parameter_table():
    assert (P0.a10, P0.a20, P0.a3, P0.a4) == (0.09, 0.4875, 0.01068, 0.004635)
    assert (P0.b1, P0.b2, P0.b3, P0.b4) == (2.0, 0.5, 0.02, 0.01)
    assert (P0.c21, P0.c32, P0.c42, P0.c43) == (0.2846, 0.002, 0.001139, 0.0025)
    assert (P0.kM, P0.kF, P0.Nmin, P0.Nmax, P0.thetaF, P0.thetaM) == (0.01, 0.019, 0.5, 1.3, 0.434, 0.469)
    assert (P0.tau_h, P0.t1, P0.tau_d, P0.beta, P0.Fmax) == (6.0, 17.0, 12.0, 0.04, 150.0)


def test_params_from_toml(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text("kM = 0.025\nb3 = 0.021\ntau_d = 10\n")
    p = signaling.load_params(path)
    assert (p.kM, p.b3, p.tau_d) == (0.025, 0.021, 10.0) and p.a10 == 0.09
    assert signaling.load_params(path, kM=0.03).kM == 0.03


@pytest.mark.parametrize(
    "text, message",
    [
        ("kM = 0.02\nspeed = 1\n", r"p.toml: unknown parameter\(s\) speed; known: Fmax, Nmax"),
        ("kM = 'fast'\n", r"p.toml: kM: expected a number"),
        ("b1 = 0\n", r"p.toml: b1 must be a finite positive number"),
        ("c32 = -1\n", r"p.toml: c32 must be >= 0"),
        ("Nmin = 1.5\n", r"p.toml: Nmin must be < Nmax"),
        ("kM = [1\n", r"p.toml: malformed TOML"),
    ],
)
def test_bad_parameter_files(tmp_path, text, message):
    path = tmp_path / "p.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        signaling.load_params(path)


def test_per_member_arrays_are_validated():
    with pytest.raises(InputError, match="differ in length"):
        signaling.SignalingParams(kM=np.ones(3), kF=np.ones(4))
    with pytest.raises(InputError, match="b2 must be a finite positive"):
        signaling.SignalingParams(b2=np.array([0.5, -0.5]))
    p = signaling.SignalingParams(kM=[0.01, 0.02])
    assert p.size == 2 and p.member(1).kM == 0.02 and p.take(np.array([1])).kM.tolist() == [0.02]
    with pytest.raises(ValueError):
        p.kM[0] = 1.0  # frozen means frozen


# --- equilibrium and closed forms --------------------------------------------------------


def test_rest_state_is_a_fixed_point():
    np.testing.assert_allclose(Y0, [0.045, 1.000614, 0.433939, 0.468985, 1.0], atol=5e-7)
    # both effectors sit just below their thresholds: no net balance at rest
    assert Y0[2] < P0.thetaF and Y0[3] < P0.thetaM
    assert signaling.net_balance(Y0[2], Y0[3], Y0[4], P0) == 0.0
    for t in (0.0, 100.0):
        f = signaling.rhs(t, Y0, P0, named("rest"))
        assert np.max(np.abs(f / Y0)) < 1e-15
    # and for per-member parameters, each at its own rest state (N moves where FOXO or mTOR
    # rest above their thresholds)
    p = signaling.SignalingParams(a3=np.array([0.0105, 0.01068, 0.011]), c21=np.array([0.2, 0.2846, 0.3]))
    y = signaling.rest_state(p)
    assert y.shape == (5, 3)
    assert np.max(np.abs(signaling.rhs(0.0, y, p, named("rest"))[:4])) < 1e-16


def test_net_balance_thresholds_and_range():
    p = P0
    assert signaling.net_balance(0.5, 0.4, 1.0, p) == pytest.approx(-p.kF * (0.5 - p.thetaF))
    assert signaling.net_balance(0.4, 0.5, 1.0, p) == pytest.approx(p.kM * (0.5 - p.thetaM))
    assert signaling.net_balance(0.4, 0.5, 1.0, p, kM=0.5) == pytest.approx(0.5 * (0.5 - p.thetaM))
    assert signaling.net_balance(0.5, 0.5, np.array([0.49, 0.5, 1.3, 1.31]), p).tolist()[::3] == [0.0, 0.0]
    assert np.all(signaling.net_balance(0.5, 0.5, np.array([0.5, 1.3]), p) != 0.0)


def test_a2_closed_form_matches_the_integral_of_the_bump():
    from scipy.integrate import quad

    protocol = Protocol((Session(10.0, 1.0, 0.8),), 60.0)
    th, t1 = P0.tau_h, P0.t1

    def integrand(s):
        return 0.5 * (-1 / th - s / th**2) * np.exp(s / th)

    for t in (5.0, 12.0, 21.0, 24.0, 30.0):
        bump = quad(integrand, -t1, t - 10.0 - t1)[0] if t >= 10 else 0.0
        assert signaling.a2(t, protocol, P0) == pytest.approx(P0.a20 + max(bump, 0.0), abs=1e-14)
    # the bump peaks near +0.10 at t_ex + 11 h and lasts about 16 h
    t = np.linspace(10.0, 40.0, 30001)
    a2 = signaling.a2(t, protocol, P0)
    assert t[np.argmax(a2)] - 10.0 == pytest.approx(t1 - th, abs=1e-3)
    assert a2.max() - P0.a20 == pytest.approx(0.1006, abs=1e-4)
    duration = signaling.bump_duration(P0)
    assert 15.0 < duration < 16.5
    assert signaling.g(duration - t1, th) == pytest.approx(signaling.g(-t1, th), rel=1e-14)
    assert np.all(a2[t > 10.0 + duration] == P0.a20)


def test_lambert_w0_is_scipys():
    from scipy.special import lambertw

    for u in -np.geomspace(1.05, 60.0, 400):
        z = u * np.exp(u)
        assert lambert_w0(z) == pytest.approx(float(lambertw(z, 0).real), rel=4e-15, abs=1e-300)
    assert lambert_w0(-1.0 / np.e + 1e-12) == pytest.approx(-1.0, abs=3e-6)


def test_a1_is_the_session_stimulus():
    protocol = named("mwf")
    assert signaling.a1(168.0, protocol, P0) == pytest.approx(0.04 * 0.8 * 150.0)
    assert signaling.a1([167.999, 169.0, 169.5], protocol, P0).tolist() == [0.09, 0.09, 0.09]


def test_switch_times():
    got = signaling.switch_times(named("mwf"), P0, 0.0, 300.0)
    d = signaling.bump_duration(P0)
    expected = sorted(x for s in (168.0, 216.0, 264.0) for x in (s, s + 12.0, s + 13.0, s + d))
    np.testing.assert_allclose(got, [x for x in expected if x < 300.0], rtol=0, atol=1e-12)
    assert signaling.switch_times(named("rest"), P0, 0.0, END).size == 0
    # bumps cut short by the next session start are no switch
    dense = Protocol((Session(0.0, 1.0, 0.8), Session(10.0, 1.0, 0.8)), 50.0)
    assert 0.0 + d not in signaling.switch_times(dense, P0, -1.0, 50.0).tolist()


# --- RK4 ---------------------------------------------------------------------------------


def test_rk4_has_order_four_on_a_smooth_stretch():
    # perturbed rest state; FOXO and mTOR stay above their thresholds: no kink in 100 h
    y0 = Y0 * np.array([1.5, 1.3, 1.15, 1.15, 1.0])
    protocol = named("rest")
    ref = signaling.reference(P0, protocol, y0, 0.0, 100.0)[1][-1]
    dts = np.array([0.4, 0.2, 0.1, 0.05])
    errors = [np.max(np.abs(signaling.integrate(P0, protocol, y0, 0.0, 100.0, dt)[1][-1] / ref - 1)) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    print(f"\nsmooth stretch: errors {[f'{e:.2e}' for e in errors]}, fitted order {slope:.3f}")
    assert 3.8 < slope < 4.3


def test_mwf_final_N_against_the_reference(mwf_reference):
    protocol = named("mwf")
    errors = {}
    for dt in (0.1, 0.05):
        n = signaling.integrate(P0, protocol, Y0, 0.0, END, dt)[1][-1, 4]
        errors[dt] = abs(n / mwf_reference[4] - 1)
    order = np.log2(errors[0.1] / errors[0.05])
    print(f"\nmwf N(1512 h): rel. error {errors[0.05]:.2e} at dt = 0.05 h, {errors[0.1]:.2e} at 0.1 h; "
          f"observed order {order:.2f}")
    assert errors[0.05] < 1e-6
    assert 3.5 < order < 4.5


def test_batch_equals_single_runs_bit_for_bit():
    protocol = named("mwf")
    # two sessions: every switch (stimulus on/off, bump start and end) and a state-dependent kink
    t_out = np.array([0.0, 170.0, 181.0, 229.5, 250.0])
    _, single = signaling.integrate(P0, protocol, Y0, 0.0, 250.0, out_times=t_out)
    _, batch = signaling.integrate(P0, protocol, np.repeat(Y0[:, None], 1000, axis=1), 0.0, 250.0, out_times=t_out,
                           backend="numpy")
    assert batch.shape == (5, 5, 1000)
    assert np.array_equal(batch, np.repeat(single[:, :, None], 1000, axis=2))
    # the same with every parameter given per member
    per_member = signaling.SignalingParams(**{f.name: np.full(1000, getattr(P0,
                                                                            f.name)) for f in dataclasses.fields(P0)})
    _, batch = signaling.integrate(per_member, protocol, Y0, 0.0, 250.0, out_times=t_out, kM=np.full(1000, P0.kM),
                           backend="numpy")
    assert np.array_equal(batch, np.repeat(single[:, :, None], 1000, axis=2))


def test_heterogeneous_batch_member_equals_its_own_run():
    rng = np.random.default_rng(1)
    n = 40
    p = signaling.SignalingParams(
        b3=P0.b3 * rng.uniform(0.9, 1.1, n),
        a20=P0.a20 * rng.uniform(0.9, 1.1, n),
        beta=P0.beta * rng.uniform(0.5, 1.0, n),
        tau_d=rng.choice([11.0, 12.0], n),  # two groups with their own switch times
    )
    kM = P0.kM * rng.uniform(0.5, 2.0, n)
    _, batch = signaling.integrate(p, named("mwf"), Y0, 0.0, 300.0, kM=kM, backend="numpy")
    for m in (0, 7, 39):
        _, one = signaling.integrate(p.member(m), named("mwf"), Y0, 0.0, 300.0, kM=float(kM[m]))
        assert np.array_equal(batch[:, :, m], one)


def test_kM_override_equals_changed_parameter():
    protocol = named("weekly")
    _, a = signaling.integrate(P0, protocol, Y0, 0.0, 400.0, kM=0.02)
    _, b = signaling.integrate(dataclasses.replace(P0, kM=0.02), protocol, Y0, 0.0, 400.0)
    assert np.array_equal(a, b)


def test_integrate_starts_anywhere_and_lands_on_output_times():
    protocol = named("mwf")
    t_out = np.array([100.0, 180.5, 200.0])
    times, y = signaling.integrate(P0, protocol, Y0, 0.0, 200.0, out_times=t_out)
    assert times.tolist() == t_out.tolist()
    # continuing from an intermediate state reproduces the run to round-off
    _, rest = signaling.integrate(P0, protocol, y[1], 180.5, 200.0)
    np.testing.assert_allclose(rest[-1], y[2], rtol=1e-13)
    with pytest.raises(ValueError, match="out_times"):
        signaling.integrate(P0, protocol, Y0, 0.0, 10.0, out_times=[5.0, 3.0])
    with pytest.raises(InputError, match="dt"):
        signaling.integrate(P0, protocol, Y0, 0.0, 10.0, dt=0.0)


# --- the compiled backend ----------------------------------------------------------------


@pytest.fixture(scope="module")
def mixed_batch():
    """300 members (one full block of the C kernel and a partial one) whose rates, stimulus,
    admissible range, stimulus delay (two timing groups) and kM differ."""
    rng = np.random.default_rng(3)
    n = 300
    p = signaling.SignalingParams(
        a20=P0.a20 * rng.uniform(0.9, 1.1, n),
        b3=P0.b3 * rng.uniform(0.9, 1.1, n),
        c43=P0.c43 * rng.uniform(0.8, 1.2, n),
        beta=P0.beta * rng.uniform(0.5, 1.0, n),
        Nmax=rng.uniform(1.0005, 1.05, n),  # some members reach the end of their range
        tau_d=rng.choice([11.0, 12.0], n),
    )
    return p, P0.kM * rng.uniform(0.5, 3.0, n)


def test_c_backend_equals_numpy_bit_for_bit(mixed_batch):
    p, kM = mixed_batch
    # the first two weeks of mwf: rest, three sessions with their switches, outputs inside
    # sessions, stimulus windows and bumps
    t_out = np.array([0.0, 100.0, 168.5, 180.25, 181.0, 200.0, 263.9, 336.0])
    _, ref = signaling.integrate(p, named("mwf"), Y0, 0.0, 336.0, out_times=t_out, kM=kM, backend="numpy")
    _, c = signaling.integrate(p, named("mwf"), Y0, 0.0, 336.0, out_times=t_out, kM=kM, backend="c")
    assert c.shape == (8, 5, 300)
    assert np.array_equal(c, ref)
    assert np.ptp(ref[-1, 4]) > 0.005  # the parameters matter
    assert np.any(ref[-1, 4] >= p.Nmax) and np.any(ref[-1, 4] < p.Nmax)  # the range limit is exercised
    # one member on C equals its plain-Python run
    _, one = signaling.integrate(p.member(7), named("mwf"), Y0, 0.0, 336.0, out_times=t_out, kM=float(kM[7]),
                                 backend="c")
    assert np.array_equal(one, ref[:, :, 7])
    with pytest.raises(InputError, match="backend must be one of numpy, c, auto"):
        signaling.integrate(p, named("mwf"), Y0, 0.0, 10.0, kM=kM, backend="fortran")


def test_auto_takes_c_for_batches_only(monkeypatch):
    if signaling.c_backend_error() is not None:
        pytest.skip(f"no C backend here: {signaling.c_backend_error()}")
    from hyper.model.signaling import compiled

    sizes = []
    run = compiled.run
    monkeypatch.setattr(compiled, "run",
                        lambda P, a20, Y0, *args, **kw: sizes.append(Y0.shape[1]) or run(P, a20, Y0, *args, **kw))
    batch = np.repeat(Y0[:, None], signaling.AUTO_MIN_MEMBERS, axis=1)
    _, auto = signaling.integrate(P0, named("mwf"), batch, 0.0, 200.0)
    _, single = signaling.integrate(P0, named("mwf"), Y0, 0.0, 200.0)
    assert sizes == [signaling.AUTO_MIN_MEMBERS]  # the single member ran in plain Python
    assert np.array_equal(auto, np.repeat(single[:, :, None], signaling.AUTO_MIN_MEMBERS, axis=2))


def test_auto_falls_back_to_numpy_without_a_compiler(monkeypatch, tmp_path, mixed_batch):
    from hyper.model.signaling import compiled

    monkeypatch.setattr(compiled, "_KERNEL", {})  # forget the kernel built so far
    monkeypatch.setenv("HYPER_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    assert "cannot build the compiled RK4 kernel" in signaling.c_backend_error()
    p, kM = mixed_batch
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, auto = signaling.integrate(p, named("mwf"), Y0, 160.0, 190.0, kM=kM)
    _, ref = signaling.integrate(p, named("mwf"), Y0, 160.0, 190.0, kM=kM, backend="numpy")
    assert np.array_equal(auto, ref)
    with pytest.raises(compiled.Unavailable, match="no-such-cc"):
        signaling.integrate(p, named("mwf"), Y0, 160.0, 190.0, kM=kM, backend="c")
    assert list(tmp_path.iterdir()) == []  # the failed builds left nothing behind


# --- N at the ends of its range -----------------------------------------------------------


def test_N_stops_at_the_bounds_it_reaches_and_leaves_them_when_f_turns():
    """FOXO above a lowered threshold drives N down to Nmin (about 100 h, held while f < 0);
    a raised mTOR growth rate turns f positive near 190 h and N climbs to Nmax (about 700 h).
    Without sessions RK4 is accurate to 1e-9 here: what is left is the bounds' handling."""
    p = dataclasses.replace(P0, a4=1.1 * P0.a4, thetaF=0.42, Nmin=0.985, Nmax=1.05)
    t = np.array([150.0, 400.0, 900.0, 1000.0])
    # a third member starts below its range, where f = 0: it keeps its N
    y0 = np.stack([Y0, Y0, [*Y0[:4], 0.9]], axis=1)
    _, ref = signaling.reference(p, named("rest"), Y0, 0.0, 1000.0, out_times=t)
    np.testing.assert_array_equal(ref[[0, 2, 3], 4], [0.985, 1.05, 1.05])  # the events stop N there
    runs = [signaling.integrate(p, named("rest"), Y0, 0.0, 1000.0, out_times=t)[1]]
    for backend in ("numpy", "c"):
        _, batch = signaling.integrate(p, named("rest"), y0, 0.0, 1000.0, out_times=t, backend=backend)
        np.testing.assert_array_equal(batch[:, 4, 2], 0.9)
        runs += [batch[:, :, 0], batch[:, :, 1]]
    for y in runs:
        np.testing.assert_array_equal(y, runs[0])  # every backend, the same bits
    N = runs[0][:, 4]
    np.testing.assert_allclose(N[[0, 2, 3]], [0.985, 1.05, 1.05], rtol=0, atol=1e-12)
    assert 1.0 < N[1] < 1.05  # released from Nmin, not yet at Nmax
    assert abs((N[1] - 1.0) - (ref[1, 4] - 1.0)) < 1e-7


# --- the original code's integration (MODEL.md §9) ----------------------------------------


def test_the_original_rk45_gives_the_original_code_s_delta_N(monkeypatch):
    """RK45 at rtol 1e-3 restarted only at session starts and ends: ΔN over nine weeks of
    mwf is the original code's 0.091496, 0.27 % above the converged 0.091245."""
    import scipy.integrate

    spans = []
    solve_ivp = scipy.integrate.solve_ivp

    def recording(fun, span, y0, **kw):
        spans.append(tuple(span))
        assert (kw["method"], kw["rtol"], kw["atol"], kw["max_step"]) == ("RK45", 1e-3, 1e-6, 0.05)
        return solve_ivp(fun, span, y0, **kw)

    monkeypatch.setattr(scipy.integrate, "solve_ivp", recording)
    protocol = named("mwf")
    y0 = signaling.start_state("rk45-original")
    np.testing.assert_array_equal(y0, [*Y0[:4], 1.000768])
    t, y = signaling.integrator("rk45-original")(P0, protocol, y0, 0.0, END, out_times=[0.0, 500.0, END])
    assert spans == [(a, b) for a, b, _ in protocol.periods()]  # no restart at the delayed switches
    assert t.tolist() == [0.0, 500.0, END] and y[0, 4] == 1.000768
    assert y[-1, 4] - y[0, 4] == pytest.approx(0.091496, abs=1e-6)
    _, rk4 = signaling.integrate(P0, protocol, Y0, 0.0, END)
    assert rk4[-1, 4] - 1.0 == pytest.approx(0.091245, abs=1e-6)
    with pytest.raises(InputError, match="signaling_method: must be one of rk4, rk45-original"):
        signaling.integrator("rk45")


def test_cli_records_the_signaling_method(tmp_path):
    import h5py

    spec = tmp_path / "mine.toml"
    spec.write_text("end = 60.0\n[[session]]\nstart = 10\nduration = 2\nintensity = 0.5\n")
    path = tmp_path / "mine.h5"
    assert signaling_job.main(["--protocol", str(spec), "--output", str(path), "--signaling-method",
                               "rk45-original"]) == 0
    with h5py.File(path) as f:
        assert f.attrs["signaling_method"] == "rk45-original" and f.attrs["integrator"] == "RK45"
        assert f["N"][0] == 1.000768


# --- the paper's results -----------------------------------------------------------------


def test_igf1_and_akt_peak_12_to_14_hours_after_a_session_start():
    protocol = named("mwf")
    for start in (168.0, 216.0):
        t = np.arange(start, start + 24.0 + 1e-9, 0.01)
        _, y = signaling.integrate(P0, protocol, Y0, 0.0, t[-1], out_times=t)
        for k in (0, 1):
            assert 12.0 <= t[np.argmax(y[:, k])] - start <= 14.0


def test_final_N_orders_the_protocols():
    final = {name: signaling.integrate(P0, named(name), Y0, 0.0, END)[1][-1, 4]
             for name in ("mwf", "every3days", "weekly", "rest")}
    print(f"\nN(1512 h): {final}")
    assert final["mwf"] > final["every3days"] > final["weekly"] > final["rest"]
    assert final["rest"] == 1.0


# --- failures ----------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["numpy", "c"])
def test_too_large_a_step_stops_with_time_and_member(backend):
    with pytest.raises(signaling.SignalingError,
                       match=r"t = 181 h to t = 181.9\d+ h gave member 0 .*smaller dt \(now 1 h\)"):
        signaling.integrate(P0, named("mwf"), Y0, 0.0, END, dt=1.0, backend=backend)
    # in a batch the failing member is named, with its state: a stronger stimulus makes member 2 stiffer
    p = signaling.SignalingParams(beta=np.array([0.04, 0.04, 0.12]))
    with pytest.raises(signaling.SignalingError,
                       match=r"t = 180.5 h to t = 181 h gave member 2 .*igf1=-1.107e\+04, akt=24.56"):
        signaling.integrate(p, named("mwf"), Y0, 0.0, 400.0, dt=0.5, backend=backend)


def test_failed_members_are_masked_the_others_untouched():
    # beta = 0.8 makes the session stimulus 96/h: RK4 with dt = 0.05 h is unstable for member 1
    # only, 12.25 h after daily15's first session starts
    p = signaling.SignalingParams(beta=np.array([0.04, 0.8, 0.04, 0.03]), kM=np.array([0.01, 0.01, 0.02, 0.015]))
    protocol, t_out = named("daily15"), np.array([0.0, 12.0, 30.0, 48.0])
    alone = [signaling.integrate(p.member(m), protocol, Y0, 0.0, 48.0, out_times=t_out,
                                 backend="numpy")[1] for m in (0, 2, 3)]
    for backend in ("numpy", "c"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no overflow warnings from the failing member
            times, y, failed = signaling.integrate(p, protocol, Y0, 0.0, 48.0, out_times=t_out, backend=backend,
                                           failures="mask")
        assert times.tolist() == t_out.tolist() and y.shape == (4, 5, 4)
        assert failed.dtype == bool and failed.tolist() == [False, True, False, False]
        assert np.all(np.isnan(y[:, :, 1]))
        for m, one in zip((0, 2, 3), alone):
            assert np.array_equal(y[:, :, m], one)
        # one member: the flag is a bool
        _, y1, f1 = signaling.integrate(p.member(1), protocol, Y0, 0.0, 48.0, backend=backend, failures="mask")
        assert f1 is True and y1.shape == (2, 5) and np.all(np.isnan(y1))
        _, y_ok, f_ok = signaling.integrate(p.member(0), protocol, Y0, 0.0, 48.0, out_times=t_out, backend=backend,
                                    failures="mask")
        assert f_ok is False and np.array_equal(y_ok, alone[0])
        with pytest.raises(signaling.SignalingError, match=r"t = 12.25 h to t = 12.3 h gave member 1 .*smaller dt"):
            signaling.integrate(p, protocol, Y0, 0.0, 48.0, backend=backend)
    with pytest.raises(InputError, match="failures must be one of raise, mask"):
        signaling.integrate(p, protocol, Y0, 0.0, 48.0, failures="nan")


# --- CLI ---------------------------------------------------------------------------------


def test_cli_writes_series_and_figure(tmp_path, capsys):
    from hyper.core import io

    out = tmp_path / "sig"
    assert signaling_job.main(["--protocol", "all", "--output", str(out), "--plot", str(out / "f.png"),
                         "--sample-every", "2"]) == 0
    for name in signaling.PAPER:
        series = io.read_series(out / f"{name}.h5")
        assert sorted(series) == sorted(["t", *signaling.STATES])
        assert series["t"][0] == 0.0 and series["t"][-1] == END
    assert (out / "f.png").stat().st_size > 10_000
    assert "mwf: N(1512 h) = 1.0912" in capsys.readouterr().out


def test_cli_protocol_file_and_bad_input(tmp_path, capsys):
    import h5py

    spec = tmp_path / "mine.toml"
    spec.write_text("end = 100.0\n[[session]]\nstart = 10\nduration = 2\nintensity = 0.5\n")
    path = tmp_path / "mine.h5"
    assert signaling_job.main(["--protocol", str(spec), "--output", str(path), "--signaling-dt", "0.1"]) == 0
    with h5py.File(path) as f:
        assert f.attrs["dt"] == 0.1 and f["protocol"].attrs["name"] == "mine"
        assert f["signaling"].attrs["kM"] == 0.01 and "version_hyper" in f.attrs
    bad = tmp_path / "bad.toml"
    bad.write_text("end = 100.0\n[[session]]\nstart = 10\nduration = -2\nintensity = 0.5\n")
    out = tmp_path / "none"
    assert signaling_job.main(["--protocol", str(bad), "--output", str(out)]) == 2
    assert "error: " in capsys.readouterr().err and not out.exists()
    params = tmp_path / "p.toml"
    params.write_text("kM = 0.01\nspeed = 2\n")
    assert signaling_job.main(["--params", str(params), "--output", str(out)]) == 2
    assert "unknown parameter(s) speed" in capsys.readouterr().err and not out.exists()
    assert signaling_job.main(["--signaling-dt", "2", "--output", str(out)]) == 3  # a run that failed, as in grow
    assert "smaller dt" in capsys.readouterr().err and not out.exists()


def test_cli_help_shows_every_default(capsys):
    with pytest.raises(SystemExit):
        signaling_job.main(["--help"])
    text = capsys.readouterr().out
    assert "--signaling-dt H      largest step (h), of either method (default: 0.05)" in text
    assert "rk45-original" in text and "(default: rk4)" in text
    assert "(default: mwf)" in text and "--protocol-file" not in text


# --- MPI: each rank integrates its share of the batch ------------------------------------


@pytest.mark.mpi
def test_batch_split_over_ranks_equals_serial():
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    n = 64
    rng = np.random.default_rng(7)
    p = signaling.SignalingParams(kM=P0.kM * rng.uniform(0.5, 2.0, n), a3=P0.a3 * rng.uniform(0.98, 1.02, n))
    mine = np.arange(comm.rank, n, comm.size)
    _, part = signaling.integrate(p.take(mine), named("mwf"), Y0, 0.0, 300.0)
    parts = comm.allgather((mine, part[-1]))
    gathered = np.empty((5, n))
    for index, values in parts:
        gathered[:, index] = values
    _, serial = signaling.integrate(p, named("mwf"), Y0, 0.0, 300.0)
    assert np.array_equal(gathered, serial[-1])


@pytest.mark.mpi
def test_ranks_building_the_kernel_at_once_get_the_same_bits(monkeypatch, tmp_path):
    from mpi4py import MPI

    from hyper.model.signaling import compiled

    comm = MPI.COMM_WORLD
    cache = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0)) / "cache"
    monkeypatch.setenv("HYPER_CACHE_DIR", str(cache))
    monkeypatch.setattr(compiled, "_KERNEL", {})  # every rank builds anew, into one empty cache
    rng = np.random.default_rng(11)
    p = signaling.SignalingParams(kM=P0.kM * rng.uniform(0.5, 2.0, 40), b4=P0.b4 * rng.uniform(0.9, 1.1, 40))
    comm.barrier()
    _, c = signaling.integrate(p, named("mwf"), Y0, 0.0, 250.0, backend="c")
    _, ref = signaling.integrate(p, named("mwf"), Y0, 0.0, 250.0, backend="numpy")
    assert np.array_equal(c, ref)
    comm.barrier()
    # one library in place, no temporary build folders left
    assert [path.suffix for path in cache.iterdir()] == [".so"]
