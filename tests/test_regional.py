"""Issue 35: the regional CSA (sections along the principal axis) and detraining (the gain's
turnover), each a switch whose default leaves today's series as they were."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import fibers, section
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import growth, signaling, surrogate
from hyper.model.protocols import Protocol, Session

# mTOR starts just above its threshold, so the muscle grows from the first hour.
GROWING = signaling.SignalingParams(thetaM=0.46)


def short_protocol() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


def run(settings: GrowthSettings, geometry: str = "cylinder", protocol=None, params=GROWING):
    g = geo.load(geometry, MPI.COMM_SELF)
    model = build_model(g, fibers.fiber_field(g), protocol or short_protocol(), params=params, settings=settings)
    return model, list(model.run())


def test_section_fractions_and_planes():
    np.testing.assert_allclose(section.section_fractions(9), np.arange(1, 10) / 10, rtol=0, atol=1e-16)
    assert len(section.section_fractions(0)) == 0
    # a box of points 0.1 long along z: planes at z = 0.01 … 0.09, normal +z
    x, y, z = np.meshgrid([0.0, 0.02], [0.0, 0.02], np.linspace(0.0, 0.1, 11), indexing="ij")
    origins, normal = section.axial_planes(np.column_stack([x.ravel(), y.ravel(), z.ravel()]),
                                           section.section_fractions(9))
    np.testing.assert_allclose(normal, [0, 0, 1], atol=1e-14)
    np.testing.assert_allclose(origins[:, 2], np.arange(1, 10) / 100, atol=1e-15)


def test_uniform_growth_of_the_cylinder_is_the_same_at_every_section():
    """Compatible growth (axial fibres, uniform ϑ): every cross-section grows by ϑ exactly,
    whatever its reference polygon (the cuts of an unstructured mesh differ by 0.5 %)."""
    model, reports = run(GrowthSettings(growth_dt=24.0))
    assert model.regional is not None and len(model.regional.fractions) == section.SECTIONS
    areas0 = model.regional.areas0
    np.testing.assert_allclose(areas0, np.pi * 0.02**2, rtol=0.05)  # radius 0.02 m, polygons inside
    last = reports[-1]
    assert last.csa_ratio > 1.0005  # it grew
    for r in reports:
        np.testing.assert_allclose(r.sections, r.sections[0], rtol=1e-11)  # the same ϑ, to round-off
        # the mid-section's facets: the same to the Newton tolerance the displacement is solved to
        np.testing.assert_allclose(r.sections, r.csa_ratio, rtol=1e-6)
    assert last.sections[0] > 1.0005


def test_no_sections_and_no_detraining_reproduce_todays_series_bit_for_bit():
    """The switches off: the same bits as the model before them, sections or not (a measure)."""
    plain = run(GrowthSettings(growth_dt=24.0, sections=0))
    measured = run(GrowthSettings(growth_dt=24.0))
    assert plain[0].regional is None and plain[1][-1].sections is None
    for a, b in zip(plain[1], measured[1], strict=True):
        assert (a.t, a.csa_ratio, a.volume_ratio, a.kM) == (b.t, b.csa_ratio, b.volume_ratio, b.kM)
        assert np.array_equal(a.states, b.states)


def test_the_switches_enter_the_digest_only_when_set():
    default = GrowthSettings().model_attributes()
    assert "sections" not in default and "detraining" not in default
    assert GrowthSettings(sections=3).model_attributes()["sections"] == 3
    assert GrowthSettings(detraining=500.0).model_attributes()["detraining"] == 500.0


@pytest.mark.parametrize("bad", [-1, 100, 2.5, True])
def test_bad_section_counts_are_refused(bad):
    with pytest.raises(InputError, match="sections"):
        GrowthSettings(sections=bad)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_detraining_time_constants_are_refused(bad):
    with pytest.raises(InputError, match="detraining"):
        GrowthSettings(detraining=bad)
    with pytest.raises(InputError, match="detraining"):
        surrogate.grow(GROWING, short_protocol(), [0.0, 96.0], detraining=bad)


def test_the_step_formula_is_the_exact_solution_for_a_constant_rate():
    """dN/dt = f − (N − 1)/τ with f constant: N − 1 = (N0 − 1) e^(−t/τ) + f τ (1 − e^(−t/τ))."""
    tau, f, N0 = 300.0, 2e-4, 1.05
    for dt in (1.0, 24.0, 168.0):
        exact = 1.0 + (N0 - 1.0) * np.exp(-dt / tau) + f * tau * (1.0 - np.exp(-dt / tau))
        assert growth.detrained(N0, f * dt, dt, tau) == pytest.approx(exact, rel=1e-14)


# Thresholds just above the rest state's (mTOR at 0.46899): the signaling falls back below them
# days after a week of training, so that f vanishes and the gain's turnover shows alone.
DETRAINED = signaling.SignalingParams(thetaM=0.472, kM=0.05)


def block() -> Protocol:
    """A week of training (Mon, Wed, Fri) and three weeks of rest."""
    return Protocol(tuple(Session(24.0 * d, 1.0, 1.0) for d in (0, 2, 4)), 4 * 168.0, "block")


def test_the_surrogates_gain_decays_with_its_time_constant_once_training_stops():
    tau = 150.0
    t = np.arange(0.0, block().end + 1.0, 24.0)
    kept = surrogate.grow(DETRAINED, block(), t)
    lost = surrogate.grow(DETRAINED, block(), t, detraining=tau, growth_dt=24.0)
    still = np.flatnonzero(np.diff(kept.N) == 0.0) + 1  # f = 0: the paper's model keeps the gain
    still = still[t[still] > 120.0]  # after the week's sessions (before the first the gain is 0)
    first = still[0]
    assert t[first] < 300.0 and np.all(np.diff(still) == 1)  # from some day after training on
    assert kept.N[-1] > 1.005 and lost.N[first] > 1.001
    expected = (lost.N[first] - 1.0) * np.exp(-(t[still] - t[first]) / tau)
    np.testing.assert_allclose(lost.N[still] - 1.0, expected, rtol=1e-12)
    np.testing.assert_allclose(lost.csa_ratio, lost.N, rtol=0)  # factor 1: the cylinder
    grown = kept.N > 1.0
    assert np.all(lost.N[grown] < kept.N[grown])  # turnover always on, sessions included
    # off: today's bits
    again = surrogate.grow(DETRAINED, block(), t, detraining=None)
    assert np.array_equal(again.N, kept.N) and np.array_equal(again.kM, kept.kM)


def test_the_coupled_cylinder_detrains_as_the_surrogate():
    """On the cylinder CSA/CSA0 = N, step for step: the coupled model's turnover is the surrogate's."""
    tau = 150.0
    model, reports = run(GrowthSettings(growth_dt=24.0, detraining=tau, sections=0), protocol=block(),
                         params=DETRAINED)
    t = np.array([r.t for r in reports])
    csa = np.array([r.csa_ratio for r in reports])
    N = np.array([r.states[4] for r in reports])
    lost = surrogate.grow(DETRAINED, block(), t, detraining=tau, growth_dt=24.0)
    np.testing.assert_allclose(N, lost.N, rtol=1e-10)  # the feedback sees the measured CSA
    np.testing.assert_allclose(csa, lost.N, rtol=1e-9)
    assert csa[-1] < csa.max() - 1e-3  # it lost what it gained


def test_a_data_file_names_its_section_and_the_comparison_uses_that_series(tmp_path):
    from hyper.runs import measured

    path = tmp_path / "mri.csv"
    path.write_text("# vastus lateralis, MRI\nsection = 0.45\n\nday,csa_change_percent\n0,0\n2,1.0\n4,2.0\n")
    data = measured.read(path)
    assert data.section == 0.45
    np.testing.assert_allclose(data.csa_ratio, [1.01, 1.02])
    t = np.array([0.0, 48.0, 96.0])
    fractions = section.section_fractions(9)
    ratios = 1.0 + np.outer(t / 96.0, fractions) * 0.1  # the change grows along the axis
    # 0.45 lies halfway between the sections at 0.4 and 0.5: the mean of their series
    got = measured.compare(data, t, np.ones(3), (fractions, ratios))
    np.testing.assert_allclose(got.model_csa_ratio, 1.0 + np.array([0.5, 1.0]) * 0.045, rtol=1e-14)
    assert got.attributes()["section"] == 0.45
    at = measured.Measured(path, "x", data.t, data.csa_ratio, 0.3)
    np.testing.assert_array_equal(measured.compare(at, t, np.ones(3), (fractions, ratios)).model_csa_ratio,
                                  ratios[1:, 2])  # a recorded section: its own series
    with pytest.raises(InputError, match="records no regional sections"):
        measured.compare(data, t, np.ones(3))
    # without a section line: the mid-belly series, as before
    path.write_text("day,csa_change_percent\n0,0\n2,1.0\n4,2.0\n")
    plain = measured.read(path)
    assert plain.section is None
    np.testing.assert_array_equal(measured.compare(plain, t, t / 96.0 + 1.0, (fractions, ratios)).model_csa_ratio,
                                  [1.5, 2.0])


@pytest.mark.parametrize("preamble, message", [
    ("section = 0\n", r"line 1: section: expected a number in \(0, 1\), got 0"),
    ("section = half\n", r"line 1: section: expected a number, got 'half'"),
    ("section = 0.5\nsection = 0.6\n", r"line 2: section given twice"),
    ("# fraction = 0.5\n", r"line 1: unknown setting 'fraction'"),
    ("a note = 1\n", r"line 1: expected a setting 'name = value' before the header"),
    ("a note\n", r"missing column 'csa'"),  # no '=': the header, whose columns are then wrong
])
def test_bad_section_lines_are_refused(tmp_path, preamble, message):
    from hyper.runs import measured

    path = tmp_path / "mri.csv"
    path.write_text(preamble + "day,csa\n0,1\n4,1.1\n")
    with pytest.raises(InputError, match=message):
        measured.read(path)


def test_the_study_of_a_run_with_the_switches_reruns_it(tmp_path):
    from hyper.analysis import study
    from hyper.runs import provenance, runspec

    settings = GrowthSettings(sections=3, detraining=500.0)
    spec = runspec.RunSpec("cylinder", short_protocol(), settings=settings)
    text = provenance.study_text(spec)
    assert "sections = 3" in text and "detraining = 500.0" in text
    assert "sections" not in provenance.study_text(runspec.RunSpec("cylinder", short_protocol()))
    path = tmp_path / "s.toml"
    path.write_text(text)
    again, _ = study.steps(study.load(path))
    assert again == settings
