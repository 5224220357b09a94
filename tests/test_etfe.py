"""ETFE against the exact sampled loop (truth: linear.z_sampled of the same loop)."""
import numpy as np
import pytest
from scipy import signal
from truthdata import PAPER_B, PAPER_M, closed_loop_recording, z_truth

from labbench.model import linear
from labbench.analysis import compare
from labbench.analysis.dataio import recording_from_arrays
from labbench.analysis.etfe import DEFAULT_ESTIMATOR, ESTIMATORS, etfe
from labbench.errors import UserError
from labbench.model.ve import Plant, VirtualEnvironment

SPRING_DAMPER = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
DAMPER = VirtualEnvironment("damper", B=1.0, w0=125.0)


def band_errors(res, ve, lo=2.0, hi=100.0):
    sel = (res.w >= lo) & (res.w <= hi)
    Zt = z_truth(ve, res.w[sel])
    return np.abs(res.Z[sel] - Zt) / np.abs(Zt), sel


@pytest.fixture(scope="module")
def runs():
    return {ve.kind: closed_loop_recording(ve) for ve in (SPRING_DAMPER, DAMPER)}


@pytest.mark.parametrize("kind", ["spring-damper", "damper"])
def test_default_meets_targets_on_clean_two_minutes(runs, kind):
    ve = SPRING_DAMPER if kind == "spring-damper" else DAMPER
    res = etfe(runs[kind])
    assert res.estimator == DEFAULT_ESTIMATOR
    err, sel = band_errors(res, ve)
    assert sel.sum() >= 50
    assert np.median(err) <= 0.01 and err.max() <= 0.05
    assert not res.low_coherence[sel].any()
    # ok over the band asked about (W_BAND) and beyond it; whatever bites outside is a note
    v = res.verdict
    assert v.level == "ok" and not v.reasons and v.band[0] <= 2.0 and v.band[1] >= 100.0, v


def test_paper_estimator_is_the_papers_method_exactly(runs):
    rec = runs["spring-damper"]
    res = etfe(rec, "paper", window=200)
    # independent transcription: DFT ratio over jw, Hamming-weighted complex moving average
    F, X = np.fft.rfft(rec.force), np.fft.rfft(rec.position)
    k = np.arange(1, len(F))
    w = 2 * np.pi * k / (len(rec.t) / rec.fs)
    raw = F[k] / (1j * w * X[k])
    h = np.hamming(200)
    ref = np.convolve(raw, h, "same") / np.convolve(np.ones(len(raw)), h, "same")
    assert np.allclose(res.w, w)
    assert np.allclose(res.Z, ref, rtol=1e-9, atol=0)
    # and it is the weak one, as docs/analysis.md says (several % median), with drift called out
    err, _ = band_errors(res, SPRING_DAMPER)
    assert np.median(err) > 0.01
    assert any(f.startswith("drift") for f in etfe(runs["damper"], "paper").flags)


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_every_estimator_gives_aligned_finite_output(runs, estimator):
    d = etfe(runs["spring-damper"], estimator).as_dict()
    n = len(d["w"])
    for key in ("Z_re", "Z_im", "ES", "ED", "EM", "coherence", "Z_err"):
        assert len(d[key]) == n and np.all(np.isfinite(d[key]))
    assert d["ws_star"] is not None and abs(d["ws_star"] - 23) < 3  # sqrt(K/m) = 23 rad/s


def test_band_covers_truth_under_position_noise(runs):
    rec = runs["spring-damper"]
    rng = np.random.default_rng(11)
    noisy = recording_from_arrays(rec.t, rec.force, rec.position + 2e-5 * rng.standard_normal(len(rec.t)))
    res = etfe(noisy)
    _, sel = band_errors(res, SPRING_DAMPER)
    inside = np.abs(res.Z[sel] - z_truth(SPRING_DAMPER, res.w[sel])) <= res.Z_err[sel]
    assert 0.85 <= inside.mean() <= 1.0  # a 95 % band, checked on ~100 frequencies
    assert np.median(res.Z_err[sel] / np.abs(res.Z[sel])) < 0.2  # and not vacuous
    # where noise dominates (high w: position ~ 1/w^2) coherence drops and is flagged
    assert res.low_coherence[res.w > 1000].any()
    assert any(f.startswith("low-coherence") for f in res.flags)


def test_quantised_position_flagged(runs):
    rec = runs["spring-damper"]
    q = recording_from_arrays(rec.t, rec.force, np.round(rec.position / 1e-5) * 1e-5)
    flags = etfe(q).flags
    assert any(f.startswith("quantised-position") for f in flags)


def test_quantised_position_is_a_limit_not_a_doubt(runs):
    # a 38 um encoder on 2 min: its noise swamps the position above ~200 rad/s, where the bands
    # widen (they still hold the truth); over the band asked about the result is exact to
    # 0.1 %: ok there, the quantisation said in a note (before: doubtful on every such run)
    rec = runs["spring-damper"]
    res = etfe(recording_from_arrays(rec.t, rec.force, np.round(rec.position / 38.3e-6) * 38.3e-6))
    err, sel = band_errors(res, SPRING_DAMPER)
    assert err.max() < 0.01 and _inside(res, SPRING_DAMPER).mean() >= 0.9
    v = res.verdict
    assert v.level == "ok" and v.band[0] <= 2 and 100 <= v.band[1] < 1000, v
    assert any("quantisation" in n and "outside the band" in n for n in v.notes), v.notes


def test_noise_free_data_are_not_doubted():
    # the plain simulator's records are the model's own: bands ~1e-8 wide, and a curvature
    # bias of 1e-10 beyond them is not a doubt (before: "narrow-band" at 2-7 rad/s, K = 200)
    ve = VirtualEnvironment("spring-damper", K=200.0, B=1.0, w0=125.0)
    res = etfe(closed_loop_recording(ve, n=120000))
    err, _ = band_errors(res, ve)
    assert err.max() < 1e-4
    assert res.verdict.level == "ok" and not res.verdict.reasons, res.verdict


def test_little_excitation_flagged_where_the_band_asked_about_reaches():
    # force low-passed at 10 Hz: nothing above ~100 rad/s is excited. Over the default band
    # (2-100 rad/s) that is a note; asked about 2-300 rad/s, the verdict doubts it
    rec = closed_loop_recording(SPRING_DAMPER, n=60000)
    sos = signal.butter(8, 10.0, fs=1000.0, output="sos")
    f = signal.sosfilt(sos, rec.force)
    _, y, _ = signal.dlsim(linear.closed_loop(Plant(PAPER_M, PAPER_B), SPRING_DAMPER).as_dlti(), f)
    data = recording_from_arrays(rec.t, f, y[:, 0])
    res = etfe(data)
    assert any(f.startswith("little-excitation") for f in res.flags)
    assert res.verdict.level == "ok" and res.verdict.band[1] < 300, res.verdict
    assert any("too little force" in n for n in res.verdict.notes)
    wide = etfe(data, band_rad_s=(2.0, 300.0)).verdict
    assert wide.level == "doubtful" and wide.band == (2.0, 300.0)
    assert any(r.startswith("little-excitation") for r in wide.reasons), wide
    with pytest.raises(UserError, match="analysis band"):
        etfe(data, band_rad_s=(300.0, 2.0))


def test_short_record_flagged():
    # 6 s resolve from ~7 rad/s: the verdict's band starts there and a note says why
    rec = closed_loop_recording(SPRING_DAMPER, n=6000)
    res = etfe(rec)
    assert any(f.startswith("short-record") for f in res.flags)
    assert res.verdict.band[0] == pytest.approx(res.w[0]) and res.w[0] > 2
    assert any(n.startswith(f"below {res.w[0]:.3g} rad/s not resolved") for n in res.verdict.notes)


def test_theory_comparison_identifies_the_device_from_the_closed_loop(runs):
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.002)
    rec = closed_loop_recording(ve, n=60000)
    ident = compare.identify_closed_loop(rec, compare.ve_from_meta(rec.meta, rec.fs))
    assert abs(ident.m / PAPER_M - 1) < 1e-3 and abs(ident.b / PAPER_B - 1) < 1e-2
    res = etfe(rec)
    cmp = compare.compare(res, Plant(ident.m, ident.b), ve)
    assert cmp["model"] == "sampled"
    assert cmp["deviation_median"] < 0.01 and cmp["deviation_max"] < 0.05


def test_constant_position_is_a_user_error():
    n = 5000
    rec = recording_from_arrays(np.arange(n) / 1000, np.ones(n) + np.arange(n) % 3, np.zeros(n))
    with pytest.raises(UserError, match="position never changes"):
        etfe(rec)


def test_bad_window():
    rec = closed_loop_recording(SPRING_DAMPER, n=5000)
    with pytest.raises(UserError):
        etfe(rec, "paper", window=1)
    with pytest.raises(UserError):
        etfe(rec, "nope")


def _noisy_position(rec, noise, seed):
    rng = np.random.default_rng(1000 + seed)  # not the record's own stream (that drew its force)
    return recording_from_arrays(rec.t, rec.force, rec.position + noise * rng.standard_normal(len(rec.t)),
                                 {**rec.meta, "force_hold": "zoh"})


def _commanded(rec):
    """The record saying its force is the command (no sensor's noise on it)."""
    return recording_from_arrays(rec.t, rec.force, rec.position, {**rec.meta, "force_hold": "zoh"})


def _inside(res, ve, lo=2.0, hi=100.0):
    sel = (res.w >= lo) & (res.w <= hi)
    return np.abs(res.Z[sel] - z_truth(ve, res.w[sel])) <= res.Z_err[sel]


def test_band_radius_has_the_noise_estimates_degrees_of_freedom():
    # the narrowest bands estimate their noise from 7 complex dof: a plug-in radius sqrt(ln 20)
    # covered 91.8 % here; the F(2, 2 dof) quantile (radius95) covers as a 95 % band should
    inside = np.concatenate([_inside(etfe(_commanded(closed_loop_recording(SPRING_DAMPER, n=30000, seed=s,
                                                                           process_noise=0.1))),
                                     SPRING_DAMPER) for s in range(20)])
    assert len(inside) > 1000 and 0.93 <= inside.mean() <= 0.97, inside.mean()


def test_h1_log_takes_its_band_averages_resolution_bias_out():
    # a flat-spectrum periodic force (unit |F_k|, random phases) in steady state: X_k = G F_k
    # bin by bin, so h1-log's band average is the mean of G over the band and what is left is
    # its resolution bias. Near the loop's anti-resonance that was 1.4 % of |Z| (median 0.3 %
    # over 2-100 rad/s); less the second-difference estimate of it, 0.23 % (0.03 %)
    n = 120000
    phase = np.random.default_rng(3).uniform(0, 2 * np.pi, n // 2 + 1)
    spectrum = np.exp(1j * phase)
    spectrum[[0, -1]] = 0.0
    f = np.fft.irfft(spectrum, n)
    f /= f.std()
    loop = linear.closed_loop(Plant(PAPER_M, PAPER_B), SPRING_DAMPER)
    _, y, _ = signal.dlsim(loop.as_dlti(), np.tile(f, 2))  # the second period is steady
    meta = closed_loop_recording(SPRING_DAMPER, n=1000).meta
    res = etfe(recording_from_arrays(np.arange(n) * SPRING_DAMPER.T, f, y[n:, 0], meta), "h1-log")
    err, _ = band_errors(res, SPRING_DAMPER)
    assert err.max() < 0.004 and np.median(err) < 0.001, (err.max(), np.median(err))


def test_a_sharp_resonance_narrows_its_bands_or_says_it_cannot():
    # a spring at 0.75 K_max, b = 0.1: a resonance 1 rad/s wide at 40 rad/s. On 2 min the bands
    # there narrow until the local model follows it (before: 20-28 % errors under 9-11 % bands,
    # issue 24) and hold the truth; on 30 s even the narrowest band spans it: the verdict says
    # so where the bias may exceed BIAS_FAR of the band's errors, else the band still holds it
    spring = VirtualEnvironment("spring", K=150.0)
    for seed in (1, 2, 3):
        res = etfe(_noisy_position(closed_loop_recording(spring, n=120000, seed=seed), 1e-5, seed))
        near = (res.w > 30) & (res.w < 50)
        err = np.abs(res.Z - z_truth(spring, res.w)) / res.Z_err
        assert err[near].max() < 2.5 and _inside(res, spring).mean() >= 0.9, (seed, err[near].max())
    for seed in (1, 2, 3):
        short = etfe(_noisy_position(closed_loop_recording(spring, n=30000, seed=seed), 1e-5, seed))
        near = (short.w > 30) & (short.w < 50)
        far = np.abs(short.Z - z_truth(spring, short.w)) / short.Z_se > 5.6  # beyond the 1e-6 tail
        said = [r for r in short.verdict.reasons if r.startswith("narrow-band")]
        assert not far[near].any() or (said and short.verdict.level == "doubtful"), (seed, short.verdict)


def test_a_local_bias_is_a_doubt_only_beyond_the_band_and_the_noise_floor():
    # the rule on the estimator's own bias estimate (lpm): doubtful where it exceeds BIAS_FAR
    # standard errors and BIAS_MATTERS of |Z|, not where the band still holds it
    from labbench.analysis import etfe as E

    w = np.geomspace(2, 100, 5)
    Z = np.full(5, 10.0 + 0j)
    se = np.full(5, 0.01 * 10.0)  # 1 % standard errors
    bias = np.array([0.005, 0.025, 0.035, 0.0005, 0.5])  # 0.5, 2.5, 3.5, 0.05, 50 se
    res = E.EtfeResult("lpm", w, Z, np.ones(5), 2 * se, se, np.zeros(5, bool),
                       unresolved=np.array([True, True, True, True, False]), bias_rel=bias)
    sharp, _ = E._sharp(res)
    assert sharp.tolist() == [False, False, True, False, False]
    tiny = E.EtfeResult("lpm", w, Z, np.ones(5), 2e-8 * np.abs(Z), 1e-8 * np.abs(Z), np.zeros(5, bool),
                        unresolved=np.ones(5, bool), bias_rel=np.full(5, 1e-4))  # noise-free data
    assert not E._sharp(tiny)[0].any()
    clean = etfe(closed_loop_recording(SPRING_DAMPER, n=60000))
    assert clean.verdict.level == "ok", clean.verdict
    d = clean.as_dict()["verdict"]
    assert d["level"] == "ok" and d["reasons"] == [] and d["band_rad_s"][0] <= 2 <= 100 <= d["band_rad_s"][1]


def test_force_sensor_noise_at_an_anti_resonance_is_held_by_the_force_reading():
    # a spring at 0.9 K_max, 30 s, 0.05 N of sensor noise on 0.25 N (issue 30's grid): at
    # 42.7 rad/s |Z| dips and the admittance peaks within a few bins, which lpm's quadratic in
    # G cannot follow: its reading is 79 % off (9.6 se), once the grid's one silent failure.
    # The fit with the noise in the force follows the smooth Z there (5 % off); the band
    # reaches it, so it holds the truth, and the verdict says where it was widened.
    ve = VirtualEnvironment("spring", K=180.0)
    rec = closed_loop_recording(ve, n=30000, seed=1, force_std=0.25)
    noise = 0.05 * np.random.default_rng(10_001).standard_normal(len(rec.t))
    res = etfe(recording_from_arrays(rec.t, rec.force + noise, rec.position, rec.meta))
    band = (res.w >= 2) & (res.w <= 100)
    truth = z_truth(ve, res.w)
    err = np.abs(res.Z - truth)
    far = band & (err / res.Z_se > 5.6) & (err > 0.01 * np.abs(truth))
    assert far.any()  # lpm's own reading misses far beyond its noise ...
    assert np.all(np.abs(res.Z_force - truth)[far] < 0.1 * np.abs(truth[far]))  # ... the force reading not
    assert np.all(err[far] <= res.Z_err[far]) and np.all(res.Z_allow[far] > 0)  # the band holds it
    assert _inside(res, ve).mean() >= 0.95
    where = [n for n in res.verdict.notes if n.startswith("band widened") and "42.7" in n]
    assert res.verdict.level == "ok" and where, res.verdict


def test_force_sensor_noise_widens_lpm_bands_and_is_a_doubt_without_a_force_reading():
    # sensor noise on a 0.25 N excitation, 2 min, biases lpm's |Z| up (errors in the
    # variables): 0.05 N by ~4 %, 0.15 N by ~36 %, against bands of ~6-17 %. lpm's bands reach
    # the reading with the noise in the force and hold the truth (ok, a note where they grew
    # beyond FORCE_NOISE_FAR se); h1-log has no such reading: a doubt where the coherence's
    # bound exceeds its band. Process noise of the same size with the force stated to be the
    # command (force_hold = zoh) biases nothing: no such finding, no widening.
    for sensor in (0.05, 0.15):
        rec = closed_loop_recording(SPRING_DAMPER, n=120000, seed=4, force_std=0.25)
        noisy = recording_from_arrays(rec.t, rec.force + sensor * np.random.default_rng(5).standard_normal(len(rec.t)),
                                      rec.position, rec.meta)
        res = etfe(noisy)
        assert _inside(res, SPRING_DAMPER).mean() >= 0.95 and res.verdict.level == "ok", res.verdict
        assert np.all(res.eiv_bound > 0) and res.Z_allow.max() > 0
        if sensor == 0.15:
            assert any(n.startswith("band widened") for n in res.verdict.notes), res.verdict
            h1 = etfe(noisy, "h1-log")
            assert h1.Z_allow is None and _inside(h1, SPRING_DAMPER).mean() < 0.5
            assert h1.verdict.level == "doubtful" and any(r.startswith("force-noise") for r in h1.verdict.reasons)
    commanded = closed_loop_recording(SPRING_DAMPER, n=120000, seed=4, force_std=0.25, process_noise=0.05)
    commanded.meta["force_hold"] = "zoh"
    res = etfe(commanded)
    assert not any("force" in r for r in res.verdict.reasons + res.verdict.notes) and not res.eiv_bound.any()
    assert res.Z_force is None and res.Z_allow is None
    assert _inside(res, SPRING_DAMPER).mean() >= 0.9


def test_error_correlation_between_bands_matches_the_records():
    # the loop fit weighs the frequencies by how their errors correlate (neighbouring bands
    # share DFT bins): the LPM's own prediction against 40 noise realisations
    dG, R = [], []
    for seed in range(40):
        res = etfe(closed_loop_recording(SPRING_DAMPER, n=30000, seed=100 + seed, process_noise=0.3))
        G, Gt = 1 / (1j * res.w * res.Z), 1 / (1j * res.w * z_truth(SPRING_DAMPER, res.w))
        dG.append((G - Gt) / (res.Z_se / (res.w * np.abs(res.Z) ** 2)))
        R.append(res.error_corr())
    dG, R = np.array(dG), np.mean(R, axis=0)
    emp = dG.T @ dG.conj() / len(dG)
    emp /= np.sqrt(np.outer(np.diag(emp).real, np.diag(emp).real))
    lag1 = np.arange(len(R) - 1)
    assert np.allclose(np.diag(R), 1.0)
    low = slice(0, 20)  # the heavily overlapping low bands, correlated 0.3-0.9
    pred, seen = R[lag1, lag1 + 1], emp[lag1, lag1 + 1]
    assert np.mean(pred[low].real) > 0.5
    assert abs(np.mean(seen[low].real) - np.mean(pred[low].real)) < 0.05
    # bands that share no bins: uncorrelated but for the sampling error of 40 realisations
    # (the mean |correlation| of independent complex errors is sqrt(pi / 160) = 0.14)
    apart = np.abs(pred) < 0.05
    assert apart.sum() > 20 and np.mean(np.abs(seen[apart])) < 0.18
