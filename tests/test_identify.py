"""Identification against exact simulated data (tests/truthdata.py)."""
import re
import tracemalloc

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from truthdata import PAPER_B, PAPER_M, chirp_recording, sensor_chirp_recording, with_noise

from labbench.readout.verdict import holds
from labbench.analysis import l1
from labbench.analysis.identify import identify
from labbench.errors import UserError


@pytest.fixture(scope="module")
def clean():
    return chirp_recording(n=30000)


@pytest.mark.parametrize("method", ["l2", "l1"])
def test_clean_chirp_within_1_percent_and_mb(clean, method):
    r = identify(clean, method=method)
    assert r.model == "mb"
    assert abs(r.m / PAPER_M - 1) < 0.01 and abs(r.b / PAPER_B - 1) < 0.01
    assert r.ci95["m"][0] <= r.m <= r.ci95["m"][1]
    assert r.flags == []
    d = r.as_dict()
    assert d["coulomb"] is None and d["offset"] is None and d["n_used"] == r.n_used


@pytest.mark.parametrize("m, b", [(0.005, 0.002), (25.0, 40.0)])
def test_any_scale(m, b):
    # grams to tens of kilograms: nothing tuned to the paper's device
    rec = chirp_recording(n=20000, m=m, b=b, amp=m * 10)
    r = identify(rec)
    assert r.model == "mb"
    assert abs(r.m / m - 1) < 0.01 and abs(r.b / b - 1) < 0.01


def test_interval_covers_truth_under_noise():
    rng = np.random.default_rng(3)
    rec = with_noise(chirp_recording(n=30000), rng, force_noise=0.05)
    r = identify(rec)
    for k, truth in (("m", PAPER_M), ("b", PAPER_B)):
        lo, hi = r.ci95[k]
        assert lo < truth < hi, (k, lo, hi)
        assert hi - lo < 0.1 * truth  # informative, not a vacuous interval


# Known-truth cases for model selection and the force_hold decision: (name, recording
# factory, true model, true Coulomb, true offset, true hold). Noise 0.05 N rms on the force
# sensor, encoder step 30 um; the "sensor" record is a continuous chirp read as sampled.
def _noisy(rec, seed, **kw):
    return with_noise(rec, np.random.default_rng(seed), **kw)


TRUTH_CASES = [
    ("clean", lambda: chirp_recording(n=30000), "mb", None, None, "zoh"),
    ("noisy", lambda: _noisy(chirp_recording(n=30000), 1, force_noise=0.05), "mb", None, None, "zoh"),
    ("quantised", lambda: _noisy(chirp_recording(n=30000), 2, quantum=30e-6), "mb", None, None, "zoh"),
    ("noisy-quantised", lambda: _noisy(chirp_recording(n=30000), 3, force_noise=0.05, quantum=30e-6),
     "mb", None, None, "zoh"),
    ("sensor", lambda: sensor_chirp_recording(), "mb", None, None, "sample"),
    ("sensor-noisy-quantised", lambda: _noisy(sensor_chirp_recording(), 4, force_noise=0.05, quantum=30e-6),
     "mb", None, None, "sample"),
    ("coulomb-0.02", lambda: chirp_recording(n=30000, coulomb=0.02), "mbc", 0.02, None, "zoh"),
    ("coulomb-0.05", lambda: chirp_recording(n=30000, coulomb=0.05), "mbc", 0.05, None, "zoh"),
    ("coulomb-0.05-noisy-quantised",
     lambda: _noisy(chirp_recording(n=30000, coulomb=0.05), 5, force_noise=0.05, quantum=30e-6),
     "mbc", 0.05, None, "zoh"),
    ("coulomb-0.2", lambda: chirp_recording(n=30000, coulomb=0.2), "mbc", 0.2, None, "zoh"),
    ("offset", lambda: chirp_recording(n=30000, coulomb=0.05, offset=0.3), "mbco", 0.05, 0.3, "zoh"),
]


@pytest.mark.parametrize("method", ["l2", "l1"])
@pytest.mark.parametrize("name, make, model, coulomb, offset, hold", TRUTH_CASES, ids=[c[0] for c in TRUTH_CASES])
def test_auto_picks_the_true_model_and_hold(name, make, model, coulomb, offset, hold, method):
    r = identify(make(), method=method)  # no force_hold in the metadata: the data decide
    assert r.force_hold["value"] == hold and r.force_hold["source"] == "cross-validation", r.force_hold
    assert r.force_hold["loss_ratio"] > 1.2, r.force_hold
    assert r.model == model, r.selection["reason"]
    assert r.selection["reason"].startswith(model + ":")
    assert abs(r.m / PAPER_M - 1) < 0.01 and abs(r.b / PAPER_B - 1) < 0.05, (r.m, r.b)
    if coulomb is not None:
        assert abs(r.params["coulomb"] / coulomb - 1) < 0.10, r.params
    if offset is not None:
        assert abs(r.params["offset"] / offset - 1) < 0.05, r.params
    d = r.as_dict()
    assert d["force_hold"]["value"] == hold and len(d["selection"]["steps"]) == 2


def test_unmodelled_coulomb_flagged():
    forced = identify(chirp_recording(n=30000, coulomb=0.05), model="mb")
    assert any(f.startswith("unmodelled-coulomb") for f in forced.flags)


def test_force_hold_given_or_from_metadata_is_used_as_is():
    rec = sensor_chirp_recording()
    assert identify(rec, hold="zoh").force_hold == {"value": "zoh", "source": "given"}
    rec.meta["force_hold"] = "zoh"
    r = identify(rec)
    assert r.force_hold == {"value": "zoh", "source": "metadata"}
    # read the wrong way, a continuous force looks like friction of ~0.025 N: the data say so
    assert identify(rec, hold="sample").model == "mb" and r.model == "mbc"
    rec.meta["force_hold"] = "foh"
    with pytest.raises(UserError, match="force_hold"):
        identify(rec)


def test_force_hold_undecided_when_the_readings_agree():
    # a slow chirp under noise: half a sample of force timing changes nothing the data can
    # see; the result says the comparison was undecided, and both readings give the same plant
    rec = with_noise(chirp_recording(n=20000, f1=0.5), np.random.default_rng(9), force_noise=0.05)
    r = identify(rec)
    assert r.force_hold["value"] == "zoh" and "undecided" in r.force_hold["source"]
    assert r.force_hold["loss_ratio"] < 1.1
    other = identify(rec, hold="sample")
    assert abs(other.m / r.m - 1) < 0.01 and abs(other.b / r.b - 1) < 0.05


def test_wrong_hold_friction_is_rejected_by_the_data():
    # the same record once read each way: the data decide for the continuous one and
    # the half-sample misalignment of the wrong reading costs orders of magnitude in CV loss
    r = identify(sensor_chirp_recording())
    assert r.force_hold["cv_loss"]["zoh"] > 100 * r.force_hold["cv_loss"]["sample"]


def test_tiny_term_is_rejected_as_too_small_to_matter():
    # 0.2 mN of true friction against a 1 N chirp: exact data support it, physics does not
    r = identify(chirp_recording(n=30000, coulomb=2e-4))
    assert r.model == "mb", r.selection["reason"]
    step = r.selection["steps"][0]
    assert step["why"] in ("too small to matter", "CV gain below the force floor")
    assert step["vs_force_rms"] < 0.005


def test_outliers_l2_flagged_l1_resists():
    rng = np.random.default_rng(4)
    rec = with_noise(chirp_recording(n=30000), rng, outlier_fraction=0.01, outlier_size=5.0)
    r2 = identify(rec, method="l2", model="mb")
    r1 = identify(rec, method="l1", model="mb")
    assert any(f.startswith("force-outliers") for f in r2.flags)
    assert abs(r1.m / PAPER_M - 1) < 0.005 and abs(r1.b / PAPER_B - 1) < 0.01
    # l2 is pulled further off than l1 and knows it (flag and/or a wide interval)
    assert abs(r2.b / PAPER_B - 1) > abs(r1.b / PAPER_B - 1)


def test_short_record_flagged():
    r = identify(chirp_recording(n=1200, f1=5.0))
    assert any(f.startswith("short-record") for f in r.flags)


def test_little_excitation_gives_wide_interval():
    rng = np.random.default_rng(5)
    rec = with_noise(chirp_recording(n=20000, amp=0.01), rng, force_noise=0.05)
    r = identify(rec, model="mb")
    assert any(f.startswith("wide-interval") for f in r.flags)


def test_quantised_position_flagged():
    rec = with_noise(chirp_recording(n=30000), np.random.default_rng(6), quantum=2e-3)
    r = identify(rec, model="mb")
    assert any(f.startswith("quantised-position") for f in r.flags)


def test_fast_l1_is_exact_against_cvxpy():
    rng = np.random.default_rng(7)
    rec = with_noise(chirp_recording(n=20000), rng, force_noise=0.02, outlier_fraction=0.02,
                     outlier_size=3.0)
    from labbench.analysis.identify import _prepare

    data = _prepare(rec, None, "zoh")
    X, y = data.design("mbc"), data.y
    fast, ref = l1.lad(X, y), l1.lad_cvxpy(X, y)
    f_fast, f_ref = l1.objective(X, y, fast), l1.objective(X, y, ref)
    assert f_fast <= f_ref * (1 + 1e-6)
    assert np.allclose(fast, ref, rtol=1e-3, atol=1e-6)


def test_solver_cvxpy_option_runs(clean):
    r = identify(chirp_recording(n=4000, f1=5.0), method="l1", model="mb", solver="cvxpy")
    assert abs(r.m / PAPER_M - 1) < 0.01


def test_bad_options(clean):
    with pytest.raises(UserError):
        identify(clean, model="mbx")
    with pytest.raises(UserError):
        identify(clean, cutoff_hz=600.0)


def test_no_motion_is_a_user_error():
    from labbench.analysis.dataio import recording_from_arrays

    n = 5000
    rec = recording_from_arrays(np.arange(n) / 1000, np.random.default_rng(0).standard_normal(n), np.zeros(n))
    with pytest.raises(UserError, match="hardly moves"):
        identify(rec)


def _lp_reference(X, y):
    """LAD as the primal LP min sum(s+ + s-), X theta + s+ - s- = y (HiGHS): theta."""
    from scipy import optimize

    n, p = X.shape
    res = optimize.linprog(np.r_[np.zeros(p), np.ones(2 * n)], A_eq=np.c_[X, np.eye(n), -np.eye(n)],
                           b_eq=y, bounds=[(None, None)] * p + [(0, None)] * 2 * n, method="highs")
    assert res.status == 0, res.message
    return res.x[:p]


def test_l1_rows_at_rest_regression():
    # Smallest case of the chirp-id crash (quantised sim, Coulomb 0.01 N, seed 3): samples at
    # rest leave subnormal regressors and ~0 force, so they had the smallest residuals and made
    # the initial basis; its solve overflowed to inf and _line_search indexed an empty cumsum.
    X = np.array([[-1.5e-317, 1.7e-320], [4.9e-318, 2.2e-320], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    y = np.array([0.0, 0.0, 1.0, 2.0, 2.5])
    theta = l1.lad(X, y)
    assert np.all(np.isfinite(theta))
    assert l1.objective(X, y, theta) == pytest.approx(0.5, rel=1e-12)  # optimum: one of the last 3 rows off by 0.5
    assert l1.objective(X, y, theta) <= l1.objective(X, y, _lp_reference(X, y)) + 1e-12


def test_l1_near_ties_do_not_cycle_regression():
    # Found by test_l1_exact_on_random_problems under load: rows 5 and 7 sit 1e-16 off the fit
    # at a degenerate vertex. Taken as signed residuals, the steps swapped them back and forth
    # until MAX_STEPS, and the LP fallback's marginals fitted 14 % worse (8.11e-7 vs 7.12e-7)
    X = np.zeros((24, 3))
    X[:, 0] = [0.0625, 0, 1, 1, 3, 0, 3, 0, 1, 0, 0, 1, 2, 0, 0, 4.5, -1, 3, 3.5, 2.75, 2.875, 5, 1.5, 0]
    X[[5, 7, 11, 13], 1:] = [[3, 1], [3.25, 1], [2, 1], [5, 1]]
    y = np.full(24, -5.960464477539063e-08)
    y[[5, 7, 11, 13]] = [5.999999935618187, 6.499999935618187, 3.999999935618187, 9.999999935618186]
    theta = l1.lad(X, y)
    assert l1.objective(X, y, theta) <= l1.objective(X, y, _lp_reference(X, y)) + 1e-12  # rounding of y ~ 10


def test_l1_lp_fallback_exact_at_any_scale():
    # HiGHS's tolerances are absolute: unscaled, its dual for y ~ 6e-8 was 50 % off and the
    # LP fallback answered 8.9e-8 against the optimum 6.0e-8 (found stress-testing l1)
    X = np.zeros((12, 3))
    X[[1, 3, 9, 10, 11]] = [[0, 3, 1], [0, 1, 1], [1, 0, 0], [0, 1, 1], [0, 2, 1]]
    y = np.zeros(12)
    y[[1, 3]] = [4.90976913e-43, 2.0 ** -24]
    f_ref = l1.objective(X, y, _lp_reference(X, y))
    assert f_ref == 2.0 ** -24
    start = np.ones(3)
    for theta in (l1.lad(X, y), l1._working_set(X, y, start),
                  l1._working_set(X * 1e6, y * 1e9, start * 1e3) / 1e3):
        assert l1.objective(X, y, theta) <= f_ref * (1 + 1e-12)


@pytest.mark.parametrize("n, start", [(200, "far"), (20000, "least squares")])
def test_l1_working_set_exact(n, start):
    # the fallback alone against the LP over all rows: exact from any start, and from a start
    # no better than the steps' (least squares) its LPs stay far smaller than the data
    rng = np.random.default_rng(n)
    X = np.column_stack([rng.standard_normal(n), rng.standard_normal(n), np.ones(n)])
    y = X @ [1.0, -2.0, 0.5] + rng.laplace(0, 0.1, n)
    theta0 = np.array([3.0, 3.0, -3.0]) if start == "far" else np.linalg.lstsq(X, y, rcond=None)[0]
    sizes = []
    real = l1.optimize.linprog

    def spy(c, *a, **kw):
        sizes.append(len(c))
        return real(c, *a, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(l1.optimize, "linprog", spy)
        theta = l1._working_set(X, y, theta0)
    # the reference: the LP over all rows (small n) or the steps' certified vertex
    ref = _lp_reference(X, y) if start == "far" else l1.lad(X, y)
    assert l1.objective(X, y, theta) <= l1.objective(X, y, ref) * (1 + 1e-12)
    if start != "far":
        assert max(sizes) <= n // 8, sizes


def test_l1_initial_basis_well_apart():
    # mbco rows from a quantised sim chirp, smallest residuals first: all four share sign(v) = +1
    # and offset 1, and the first two are near copies. Gram-Schmidt projected once let rounding
    # pass the 4th as new (the basis was exactly singular: LP fallback, 3x slower identify).
    X = np.array([[6.3258525774372021e-03, 1.0957942827068612e-02, 1.0, 1.0],
                  [6.3274694962756062e-03, 1.0945120077333111e-02, 1.0, 1.0],
                  [9.3494099723430424e-03, 3.7596419337757644e-03, 1.0, 1.0],
                  [-7.8119214636587779e+00, 1.5259631901508308e-01, 1.0, 1.0],
                  [10.94, -0.45, -1.0, 1.0], [-3.0, 0.3, 1.0, 1.0], [5.0, -0.2, -1.0, 1.0]])
    B = l1._initial_basis(X, np.arange(len(X), dtype=float))
    assert np.linalg.cond(X[B] / np.abs(X).max(axis=0)) < 1e4  # near copy skipped: 1.2e7 before


def test_l1_tied_vertex_solved_without_lp(monkeypatch):
    # min |t| + |1 - 2t| + |2t|: at the optimum t = 0 two residuals are zero (a degenerate
    # vertex); treating the tie as sign 0 gave a non-descending pivot that cycled until the
    # LP fallback. Now the slope counts the tie and the small certificate LP settles it.
    monkeypatch.setattr(l1, "_working_set", lambda *a: pytest.fail("fell back to the LP"))
    X, y = np.array([[1.0], [2.0], [2.0]]), np.array([0.0, 1.0, 0.0])
    assert l1.lad(X, y)[0] == 0.0


def test_l1_never_solves_an_lp_over_all_samples(monkeypatch):
    # A clean 60 s chirp (residuals of 1e-13 beside forces of 1: ties at rounding level) stalled
    # at a tied vertex and fell back to an LP over 47 904 samples, whose cost grew as n^2 (19 s
    # at 90 000, minutes on a long record). The tied vertex's own small LP now steps on.
    sizes = []
    real = l1.optimize.linprog

    def spy(c, *a, **kw):
        sizes.append(len(c))
        return real(c, *a, **kw)

    monkeypatch.setattr(l1.optimize, "linprog", spy)
    monkeypatch.setattr(l1, "_working_set", lambda *a: pytest.fail("the steps stalled"))
    rec = chirp_recording(n=60000)
    tracemalloc.start()
    try:
        r = identify(rec, method="l1")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert abs(r.m / PAPER_M - 1) < 1e-6 and abs(r.b / PAPER_B - 1) < 1e-4
    assert max(sizes, default=0) < 100, sizes
    assert peak < 48e6, peak  # memory linear in the record: ~11 MB measured (a column is 0.5 MB)


def test_l1_line_search():
    # breakpoints t = 1, 2, 3 with weights 1, 1, 1: slope -2*1.5 reaches 0 at the second
    r, a = np.array([1.0, 2.0, 3.0]), np.ones(3)
    assert l1._line_search(r, a, 1.5) == 1
    assert l1._line_search(r, -a, 1.5) == -1  # all behind: only after an overflow
    assert l1._line_search(np.full(3, np.nan), a, 1.5) == -1


@st.composite
def _lad_problems(draw):
    """Small LAD problems with the features of identification data: integer grids (ties,
    degenerate vertices), sign and constant columns (models mbc, mbco), rows at rest
    (subnormal regressors), columns of very different scales."""
    n_free = draw(st.integers(1, 2))
    structure = draw(st.sampled_from(["", "s", "so"]))
    p = n_free + len(structure)
    n = draw(st.integers(p + 1, 30))
    grid = draw(st.booleans())
    elem = (st.integers(-3, 3).map(float) if grid
            else st.floats(-5, 5).map(lambda v: v if abs(v) > 1e-3 else 0.0))  # no 1e-300 columns
    free = draw(hnp.arrays(float, (n, n_free), elements=elem))
    cols = [free] + [np.sign(free[:, -1:]) if c == "s" else np.ones((n, 1)) for c in structure]
    X = np.hstack(cols)
    rest = draw(st.integers(0, n - p - 1))
    X[:rest, :n_free] *= 1e-318  # at rest: the filtered regressors underflow
    assume(np.linalg.cond(X[rest:]) < 1e6)  # the moving samples pin every parameter
    theta = draw(hnp.arrays(float, p, elements=st.floats(-3, 3)))
    noise = draw(hnp.arrays(float, n, elements=(st.integers(-2, 2).map(lambda k: 0.5 * k) if grid
                                                else st.floats(-1, 1, allow_subnormal=False))))
    units = 10.0 ** draw(hnp.arrays(int, p, elements=st.integers(-6, 6)))  # columns in any units
    return X * units, X @ theta + noise


@settings(max_examples=250, deadline=None)
@given(_lad_problems())
def test_l1_exact_on_random_problems(problem):
    X, y = problem
    theta = l1.lad(X, y)
    assert np.all(np.isfinite(theta))
    f_ref = l1.objective(X, y, _lp_reference(X, y))
    assert l1.objective(X, y, theta) <= f_ref + 1e-9 * (1 + np.abs(y).sum())


def _long_lad_problem(kind: str, n: int = 40000):
    """A long identification-like LAD problem (chirp regressors, sign and offset columns)."""
    rng = np.random.default_rng(sum(map(ord, kind)))  # a seed per kind, the same every run
    t = np.arange(n) / 1000.0
    v = np.sin(2 * np.pi * (0.2 + 0.05 * t) * t)
    a = np.gradient(v, t)
    X = np.column_stack([a, v, np.sign(v), np.ones(n)])
    y = X @ [0.094, 0.1, 0.02, -0.003]
    if kind == "laplace":
        y += rng.laplace(0, 0.01, n)
    elif kind == "outliers":
        y += rng.normal(0, 0.01, n) + np.where(rng.random(n) < 0.05, rng.normal(0, 2.0, n), 0.0)
    elif kind == "quantised":  # integer forces: ties everywhere, degenerate vertices
        y = np.round(100 * (y + rng.normal(0, 0.01, n))) / 100
    elif kind == "at rest":  # a tenth of the samples at rest: subnormal regressors, zero force
        y += rng.normal(0, 0.01, n)
        X[: n // 10, :2] *= 1e-318
        y[: n // 10] = 0.0
    elif kind == "clean":  # residuals at rounding level
        y += 1e-13 * rng.standard_normal(n)
    return np.asfortranarray(X), y


@pytest.mark.parametrize("kind", ["laplace", "outliers", "quantised", "at rest", "clean"])
def test_l1_on_a_long_record_is_the_exact_lad_of_every_row(kind, monkeypatch):
    # Portnoy-Koenker globbing (l1._globbed): the fit of a band of rows plus the globbed rows'
    # linear term is the exact LAD of all rows, the steps running over far fewer than n of them
    X, y = _long_lad_problem(kind)
    n = len(y)
    assert n >= l1.GLOB_ROWS
    exact = l1._rows(X, y)  # the steps over every row, certified
    fitted = []
    real = l1._simplex

    def spy(Xs, ys, B, check=l1._no_check, glob=None):
        fitted.append(len(ys))
        return real(Xs, ys, B, check, glob)

    monkeypatch.setattr(l1, "_simplex", spy)
    theta = l1.lad(X, y)
    f, f_exact = l1.objective(X, y, theta), l1.objective(X, y, exact)
    # to the rounding of the sum itself (the clean case's optimum is 3e-9 beside sum |y| = 4e3)
    assert f <= f_exact * (1 + 1e-12) + 64 * np.finfo(float).eps * np.abs(y).sum(), (f, f_exact)
    if kind != "clean":
        assert max(fitted) < n // 4, fitted  # never the fit over every row


def test_l1_from_a_far_start_on_a_long_record_is_still_exact():
    # a start far from the fit: the band's problem is unbounded or many globbed rows change
    # sign; the band grows and, at worst, every row is fitted
    X, y = _long_lad_problem("laplace")
    theta = l1.lad(X, y, theta0=np.array([5.0, -3.0, 1.0, 2.0]))
    assert l1.objective(X, y, theta) <= l1.objective(X, y, l1._rows(X, y)) * (1 + 1e-12)


ENCODER_Q = 2 * np.pi * 0.1 / 16384  # the default rig's encoder step at the handle [m]


@pytest.mark.parametrize("method", ["l2", "l1"])
def test_stick_slip_flagged_when_friction_holds_the_handle(method):
    # Fc = 0.1 N against a 0.15 N chirp: the handle sticks whenever |f| <= Fc, where
    # f = m x'' + b x' + Fc sign(x') does not hold; the fit goes wrong and must say so
    rec = with_noise(chirp_recording(n=30000, coulomb=0.1, amp=0.15, f1=10.0),
                     np.random.default_rng(0), quantum=ENCODER_Q)
    r = identify(rec, model="mbc", method=method)
    lo, hi = r.ci95["b"]
    assert abs(r.b / PAPER_B - 1) > 0.1 or hi - lo > PAPER_B  # the doubtful number this flag is about
    assert any(f.startswith("stick-slip") for f in r.flags), r.flags


@pytest.mark.parametrize("coulomb, amp, quantum", [(0.0, 1.0, 0.0), (0.0, 1.0, ENCODER_Q),
                                                   (0.05, 1.0, 0.0), (0.1, 1.0, ENCODER_Q)])
def test_no_stick_slip_flag_when_the_handle_keeps_moving(coulomb, amp, quantum):
    rec = with_noise(chirp_recording(n=30000, coulomb=coulomb, amp=amp),
                     np.random.default_rng(0), quantum=quantum)
    r = identify(rec, model="mbc")
    assert not any(f.startswith("stick-slip") for f in r.flags), r.flags


@pytest.mark.parametrize("coulomb_n", [0.0, 0.1])
def test_stick_slip_on_the_simulated_chirp_id(coulomb_n):
    # the bench's own path (protocol chirp-id on the quantised simulator): with 0.1 N of
    # friction b comes out ~4-5x too high, and the flag says why; without it, no flag
    from labbench.rig import rig_from_dict
    from labbench.runner import run
    from labbench.registry import make_protocol
    from labbench.sim_backend.sim_device import open_sim

    rig = rig_from_dict({"sim": {"quantize": True, "coulomb_n": coulomb_n}})
    res = run(open_sim(rig, seed=4), make_protocol("chirp-id", model="mbc"), [], rig=rig)
    for fit in res.results["identification"].values():
        flagged = any(f.startswith("stick-slip") for f in fit["flags"])
        assert flagged == (coulomb_n > 0), fit["flags"]
        if not flagged:
            assert abs(fit["b"] / PAPER_B - 1) < 0.02


@pytest.mark.parametrize("delay_samples", [0.0, 1.0, 1.5, 3.25])
def test_plant_force_delays_by_fractions_of_a_sample_exactly_on_a_ramp(delay_samples):
    # the split delay (1 - alpha) u[k - d] + alpha u[k - d - 1] is exact on a ramp
    from labbench.analysis.compare import _delayed

    T = 1e-3
    u = np.arange(100, dtype=float)
    late = _delayed(u, delay_samples * T, T)
    k = np.arange(10, 100)
    np.testing.assert_allclose(late[k], k - delay_samples, atol=1e-9)
    assert np.all(late[: int(delay_samples)] == 0)


def test_verdict_ok_on_clean_and_noisy_records_within_tolerance():
    # known truth: where m is within 1 % and b within 2 % and the record vouches for that (99.9 %
    # intervals inside the targets), nothing is wrong to say; 20 s under 0.2 N cannot vouch for
    # b to 2 % and says so
    rng = np.random.default_rng(3)
    for rec in (chirp_recording(n=20000), with_noise(chirp_recording(n=30000), rng, force_noise=0.02)):
        r = identify(rec)
        assert abs(r.m / PAPER_M - 1) < 0.01 and abs(r.b / PAPER_B - 1) < 0.02
        assert r.verdict.level == "ok", r.verdict
        assert r.as_dict()["verdict"] == {"level": "ok", "reasons": []}
    # 20 s under 0.2 N cannot pin b to 2 %: its interval says so, and a note says it against
    # the target; the number is not in doubt (issue 30: precision is not a doubt)
    r = identify(with_noise(chirp_recording(n=20000), rng, force_noise=0.2))
    assert r.verdict.level == "ok" and r.verdict.notes[0].startswith("b not pinned"), r.verdict
    assert holds(r.b, r.ci95["b"], PAPER_B, 0.02 * PAPER_B)


def test_verdict_names_an_unstated_device_delay():
    # a device that applies its command one period late, read without that delay: b is off
    # by ~13 % (beyond the 2 % tolerance), and the verdict says why rather than staying silent
    from truthdata import chirp_force, open_loop

    from labbench.analysis.dataio import recording_from_arrays

    n, fs = 30000, 1000.0
    f = chirp_force(n, fs)
    x, _ = open_loop(np.concatenate([[0.0], f[:-1]]), PAPER_M, PAPER_B, fs)
    r = identify(recording_from_arrays(np.arange(n) / fs, f, x, {"fs": fs, "force_hold": "zoh"}, "late"),
                 model="mb")
    assert abs(r.b / PAPER_B - 1) > 0.02
    assert r.verdict.level == "doubtful"
    said = [s for s in r.verdict.reasons if s.startswith("residual structure")]
    assert said, r.verdict
    # it even says how large: the x''' coefficient reads the delay to a few % (truth 1 ms)
    assert abs(float(re.search(r"delay of ([0-9.]+) ms", said[0]).group(1)) - 1.0) < 0.05


def test_verdict_failed_when_no_mass_is_identified():
    # a heavily damped device under a slow chirp and force noise: the inertia is ~1 % of the
    # force and the noise hides it; m's interval reaches below 0, so m is failed, not flagged
    rec = with_noise(chirp_recording(n=20000, b=20.0, f1=0.2), np.random.default_rng(2), force_noise=0.3)
    r = identify(rec, model="mb")
    assert r.ci95["m"][0] < 0 < r.ci95["m"][1]
    assert r.verdict.failed and "no mass identified" in r.verdict.reasons[0]


@pytest.mark.parametrize("n", [20000, 60000])
def test_no_outlier_flag_on_a_clean_record_with_friction(n):
    # Coulomb steps at each velocity reversal are model, not spikes (issue 24: a false
    # force-outliers flag on a clean record with Fc = 0.2 N)
    r = identify(chirp_recording(n=n, coulomb=0.2))
    assert r.model == "mbc" and not any(f.startswith("force-outliers") for f in r.flags), r.flags
    assert not any("outliers" in s for s in r.verdict.reasons) and abs(r.params["coulomb"] / 0.2 - 1) < 0.02


def test_encoder_step_is_corrected_in_l2_and_flagged_in_l1():
    # a 30 um encoder step reads x'' with noise that attenuates least squares' m by its share
    # (~0.02 % here, 3x the interval): l2 removes it (corrected least squares, the noise
    # variance known from the step), l1 cannot and says so
    base = chirp_recording(n=30000)
    err, hits = [], 0
    for seed in range(10):
        r = identify(with_noise(base, np.random.default_rng(seed), force_noise=0.01, quantum=30e-6))
        err.append(r.m / PAPER_M - 1)
        hits += r.ci95["m"][0] <= PAPER_M <= r.ci95["m"][1]
        assert r.verdict.level == "ok", r.verdict
    assert abs(np.mean(err)) < 5e-5 and hits >= 8, (np.mean(err), hits)  # uncorrected: -2.1e-4, 5 of 10
    l1_fit = identify(with_noise(base, np.random.default_rng(0), force_noise=0.01, quantum=30e-6), method="l1")
    assert any(f.startswith("quantised-position") and "l2 corrects it" in f for f in l1_fit.flags), l1_fit.flags


def test_a_sampled_force_is_differentiated_to_fourth_order():
    # a continuous chirp read at the samples: the 3-point second difference reads x'' high by
    # (w T)^2 / 12 and m with it (+0.045 %, beyond its interval); the 5-point one does not
    r = identify(sensor_chirp_recording(), hold="sample")
    assert abs(r.m / PAPER_M - 1) < 1e-5 and abs(r.b / PAPER_B - 1) < 1e-5, (r.m / PAPER_M - 1, r.b / PAPER_B - 1)


def test_friction_intervals_cover_the_fit_away_from_velocity_reversals():
    # 0.2 N of friction under a 1 N chirp: near reversals the handle sticks and the sampled
    # friction model is least exact, which pulls m by ~0.8 % on exact data; the intervals also
    # cover the fit away from the reversals, so they hold the truth, and b is not vouched for
    for n in (20000, 30000):
        r = identify(chirp_recording(n=n, coulomb=0.2))
        assert r.model == "mbc" and abs(r.m / PAPER_M - 1) > 0.005
        for k, truth in (("m", PAPER_M), ("b", PAPER_B), ("coulomb", 0.2)):
            assert r.ci95[k][0] <= truth <= r.ci95[k][1], (n, k, r.ci95[k])
        assert any(s.startswith("b not pinned") for s in r.verdict.notes), r.verdict


def test_velocity_beyond_the_filter_is_what_the_filter_leaves_of_a_driven_mass():
    # a mass-damper (corner b / m = 12 rad/s, far below the 50 Hz cut-off) under held white
    # noise, exact at the samples: the rms of v - L v is the mass's velocity beyond the filter
    from scipy import signal

    from labbench.analysis.derivatives import lowpass, velocity_beyond

    fs, m, b = 1000.0, PAPER_M, PAPER_B + 1.0
    f = 0.5 * np.random.default_rng(5).standard_normal(60000)
    a = np.exp(-b / m / fs)
    v = signal.lfilter([0.0, (1 - a) / b], [1.0, -a], f)
    assert velocity_beyond(f, fs, 50.0, m) == pytest.approx(np.std(v - lowpass(v, fs, 50.0)), rel=0.01)
    chirp = chirp_recording(n=30000)  # a band-limited force: next to nothing beyond the filter
    assert velocity_beyond(chirp.force, fs, 50.0, m) < 1e-3 * np.std(np.diff(chirp.position)) * fs


@pytest.mark.parametrize("coulomb", [0.02, 0.05])
def test_white_noise_coulomb_is_read_through_the_velocity_the_filter_leaves_out(coulomb):
    # issue 41: under white noise the velocity crosses zero on a time scale the 50 Hz derivative
    # filter does not resolve (5 mm/s of it lies beyond the cut-off), so the filtered velocity's
    # sign over-states where friction switched: Fc read 0.0165 for 0.02 N and 0.037 for 0.05,
    # b 1.19 / 1.52 for 1.1, outside their intervals. The sign's expectation given that velocity
    # (regression calibration) reads Fc within 1 % and b within 2 % here, intervals holding both.
    from truthdata import open_loop

    from labbench.analysis.dataio import recording_from_arrays

    n, b = 30000, PAPER_B + 1.0
    f = 0.5 * np.random.default_rng(7).standard_normal(n)
    x, _ = open_loop(f, PAPER_M, b, 1000.0, coulomb)
    rec = with_noise(recording_from_arrays(np.arange(n) / 1000.0, f, x, {"fs": 1000.0}, "<white truth>"),
                     np.random.default_rng(0), quantum=ENCODER_Q)
    r = identify(rec, model="mbc")
    assert r.params["coulomb"] == pytest.approx(coulomb, rel=0.03)
    assert r.ci95["coulomb"][0] <= coulomb <= r.ci95["coulomb"][1]
    assert r.ci95["b"][0] <= b <= r.ci95["b"][1]


def test_intervals_cover_over_seeds_and_a_vouched_result_meets_its_target():
    # 20 records under 0.2 N of force noise: the sandwich intervals (influence function summed
    # over blocks, Satterthwaite's dof: a chirp's damping is told by its first seconds) cover,
    # every record outside the targets (m 1 %, b 2 %) says it is not pinned to them, and an ok
    # one holds (within its target or its 99.9 % interval: verdict.holds)
    base = chirp_recording(n=30000)
    hits = {"m": 0, "b": 0}
    for seed in range(20):
        r = identify(with_noise(base, np.random.default_rng(300 + seed), force_noise=0.2))
        for k, truth in (("m", PAPER_M), ("b", PAPER_B)):
            hits[k] += r.ci95[k][0] <= truth <= r.ci95[k][1]
        outside = abs(r.m / PAPER_M - 1) > 0.01 or abs(r.b / PAPER_B - 1) > 0.02
        assert not outside or any("not pinned" in n for n in r.verdict.notes), (seed, r.m, r.b)
        held = holds(r.m, r.ci95["m"], PAPER_M, 0.01 * PAPER_M) and holds(r.b, r.ci95["b"], PAPER_B, 0.02 * PAPER_B)
        assert held or r.verdict.level != "ok", (seed, r.m, r.b)
    assert hits["m"] >= 17 and hits["b"] >= 17, hits


def test_closed_loop_identification_uses_instruments_against_process_noise():
    # 0.3 N the plant feels and the record lacks drives the motion the VE force is computed
    # from: least squares read m 6 % low, far outside its interval; the instruments (the loop's
    # response to the exogenous force alone) do not follow that noise
    from truthdata import closed_loop_recording

    from labbench.analysis import compare
    from labbench.model.ve import VirtualEnvironment

    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.001)
    rec = closed_loop_recording(ve, n=30000, seed=1, process_noise=0.3)
    plant, _ = compare.plant_recording(rec)
    plain = identify(plant, model="mb")
    assert plain.m < 0.97 * PAPER_M and not plain.ci95["m"][0] <= PAPER_M <= plain.ci95["m"][1]
    iv = identify(plant, model="mb", response=compare.loop_response(rec, ve))
    assert abs(iv.m / PAPER_M - 1) < 0.01 and iv.ci95["m"][0] <= PAPER_M <= iv.ci95["m"][1]
    assert iv.ci95["b"][0] <= PAPER_B <= iv.ci95["b"][1]
    assert "instrumental" in iv.selection["estimator"]
    l1_fit = identify(plant, model="mb", method="l1", response=compare.loop_response(rec, ve))
    assert any(f.startswith("closed-loop-l1") for f in l1_fit.flags)


def test_intervals_hold_a_parameter_whose_information_sits_in_a_few_windows():
    # a chirp tells its damping in its slow first seconds: a few interval windows carry b, and
    # their fitted residuals were pulled towards them. Here the second column lives in the
    # first sixteenth of the record (about six windows) under serially correlated noise: the
    # windows' sums without their leverage correction covered 90.3 % of 1000 draws, with it
    # 93.3 % (on 300 chirps of the method map: b 93.7 -> 95.0 % with l2, 90.0 -> 93.7 % with l1)
    from labbench.analysis.identify import _sandwich_ci, least_squares

    rng = np.random.default_rng(0)
    n, hits, widths, errors = 4000, 0, [], []
    for _ in range(1000):
        x2 = np.zeros(n)
        x2[:n // 16] = rng.standard_normal(n // 16)
        X = np.asfortranarray(np.column_stack([rng.standard_normal(n), x2]))
        y = X @ [1.0, 2.0] + np.convolve(rng.standard_normal(n + 7), np.ones(8) / 8, "valid")
        theta = least_squares(X, y)
        lo, hi = _sandwich_ci(X, y - X @ theta, theta, "l2", np.zeros(2), 4.0, np.arange(n))[1]
        hits += lo <= 2.0 <= hi
        widths.append(hi - lo)
        errors.append(theta[1] - 2.0)
    assert hits >= 920, hits
    assert np.mean(widths) < 1.3 * 2 * 1.96 * np.std(errors)  # and not by being wide
