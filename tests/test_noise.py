"""The force-noise model (labbench.model.noise) against exact truth and the rough simulator,
and the estimator of a record's force noise (labbench.analysis.force_noise)."""
import math

import numpy as np
import pytest
from scipy import signal

from labbench import records
from labbench.analysis import force_noise
from labbench.errors import UserError
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.model import linear, noise
from labbench.rig import Rig
from labbench.sim_backend.sim_device import open_sim
from labbench.model.ve import Plant, VirtualEnvironment

PLANT = Plant(0.094, 0.10)
RIG = Rig()
DELTA = RIG.metres_per_count  # 38.3 um
WIDE = SafetyConfig(force_limit_n=1e3, force_rate_limit_n_per_s=1e9, velocity_limit_m_s=1e3,
                    position_limits_m=(-1e3, 1e3), energy_limit_j=1e3, watchdog_s=1.0,
                    enable_force_threshold_n=1e-12)
BAND = noise.FELT_BAND_HZ


def sd(B, w0, **kw):
    return VirtualEnvironment("spring-damper", K=50.0, B=B, w0=w0, **kw)


def responses(ve, n, latency_samples=0):
    """Impulse responses of the real loop (HapticLoop on the ideal simulator) from a position
    error e (added to what the device reports) and from a force entering the plant with the
    command, each to the command: the exact truth the model's transfer functions must equal."""
    out = []
    for which in ("e", "n"):
        dev = open_sim(RIG, m=PLANT.m, b=PLANT.b, extra_delay_samples=latency_samples)
        dev.enable()
        loop = HapticLoop(ve, WIDE)
        u = np.empty(n)
        for k in range(n):
            seq, t, x, _ = dev.read_raw(1.0)
            pulse = 1.0 if k == 1 else 0.0
            e, f = (pulse, 0.0) if which == "e" else (0.0, pulse)
            u[k] = loop.step(seq, t, x + e, f)
            dev.command(u[k])
        # a force pulse reaches the command as f/(1+L): less the pulse, -L/(1+L) f
        out.append(u if which == "e" else u - np.where(np.arange(n) == 1, 1.0, 0.0))
    return out


@pytest.mark.parametrize("ve,latency_samples", [
    (sd(0.0, 60.0), 0), (sd(1.0, 125.0), 0), (sd(2.0, 500.0), 0),
    (sd(1.0, 125.0, td=0.002), 0), (sd(1.0, 250.0), 1),
    (VirtualEnvironment("damper", B=1.0, w0=250.0), 0)], ids=str)
def test_spectrum_and_rms_equal_the_real_loops_impulse_responses(ve, latency_samples):
    """Truth: the command's responses to an impulse of position error and of force, from the
    real loop chain on the ideal simulator. Full-band variance sigma^2 sum h^2 (Parseval) and
    the band's power from the responses' DFT, against the model's integrals: within 1e-4."""
    n = 40_000  # 40 s: the slowest mode here (B = 0: 2 s ring-down) has died out
    h_e, h_n = responses(ve, n, latency_samples)
    src = noise.NoiseSources(DELTA, 0.002)
    latency = latency_samples * ve.T
    pred = noise.force_noise(PLANT, ve, src, BAND, latency=latency)
    var_e, var_n = DELTA**2 / 12, 0.002**2
    total = var_e * np.sum(h_e**2) + var_n * np.sum(h_n**2)
    assert pred.rms_command_total == pytest.approx(math.sqrt(total), rel=1e-4)
    f = np.fft.rfftfreq(n, ve.T)
    psd = 2 * ve.T * (var_e * np.abs(np.fft.rfft(h_e)) ** 2 + var_n * np.abs(np.fft.rfft(h_n)) ** 2)
    sel = (f >= BAND[0]) & (f <= BAND[1])
    assert pred.rms_command == pytest.approx(math.sqrt(np.sum(psd[sel]) / (n * ve.T)), rel=1e-4)
    # the spectrum itself, at the model's own frequencies
    model = np.interp(f[sel], pred.f_hz, pred.psd_command)
    assert np.max(np.abs(model / psd[sel] - 1)) < 2e-3


def test_a_held_white_force_has_its_variance_over_all_images():
    """sinc^2 over all image bands sums to 1: the held force of white noise alone (no VE: the
    loop passes it untouched) carries sigma^2 from 0 to infinity; 0-500 Hz at 1 kHz holds the
    integral of sinc^2 over f T in [-1/2, 1/2] (by quadrature here)."""
    ve = VirtualEnvironment("none")
    fn = noise.force_noise(PLANT, ve, noise.NoiseSources(0.0, 0.01), (0.0, 500.0))
    x = np.linspace(0, 0.5, 200_001)
    share = np.trapezoid(np.sinc(x) ** 2, x) * 2  # one-sided: 2 T sigma^2 over f = x / T
    assert fn.parts["amplifier"] == pytest.approx(0.01 * math.sqrt(share), rel=1e-4)
    assert fn.parts["quantisation"] == 0.0
    wide = noise.force_noise(PLANT, ve, noise.NoiseSources(0.0, 0.01), (0.0, 20_000.0))
    # all but sinc^2's tail beyond x0 = 20 kHz T: 2 int_x0^inf sin^2 / (pi x)^2 ~ 1 / (pi^2 x0)
    assert wide.rms_felt == pytest.approx(0.01 * math.sqrt(1 - 1 / (math.pi**2 * 20)), rel=1e-4)


def test_error_correlation_limits_and_the_white_speed():
    rho = noise.error_correlation([0.0, (0.1 * DELTA) ** 2, (0.3 * DELTA) ** 2, DELTA**2], DELTA)
    assert rho[0] == pytest.approx(1.0, abs=2e-4)
    assert 1 > rho[1] > rho[2] > rho[3] > 0
    # increments well within a step: the sawtooth's autocorrelation 1 - 6 u (1 - u), u = |d| /
    # Delta, averaged: 1 - 6 (E|d| / Delta - E d^2 / Delta^2) (mass beyond one step: e^-50)
    assert rho[1] == pytest.approx(1 - 6 * (0.1 * math.sqrt(2 / math.pi) - 0.01), abs=1e-6)
    assert rho[3] == pytest.approx(6 / math.pi**2 * math.exp(-2 * math.pi**2), rel=1e-6)
    v = noise.white_speed(DELTA, 0.001)
    rho_at = noise.error_correlation((v * 0.001) ** 2, DELTA)[0]
    assert rho_at == pytest.approx(noise.WHITE_RHO, rel=1e-6)
    assert v == pytest.approx(0.456 * DELTA / 0.001, rel=0.01)


def test_the_error_correlation_matches_a_monte_carlo_of_rounding():
    """rho_1 of the rounding error of a Gaussian random walk's samples, counted."""
    rng = np.random.default_rng(5)
    for step in (0.15, 0.3, 0.5):
        x = np.cumsum(rng.normal(0, step, 400_000)) + rng.uniform(0, 1)
        e = x - np.round(x)
        measured = np.corrcoef(e[:-1], e[1:])[0, 1]
        assert measured == pytest.approx(noise.error_correlation(step**2, 1.0)[0], abs=0.01)


def rough_run(ve, std, seed, n=120_000, **opts):
    """A white-noise run on the rough simulator: quantised encoder, 2 mN force noise."""
    exc = np.random.default_rng(seed).normal(0.0, std, n)
    exc[0] = 0.0
    pages = []
    dev = open_sim(RIG, seed=seed, m=PLANT.m, b=PLANT.b, quantize=True, force_noise_n=0.002, **opts)
    run_loop(dev, HapticLoop(ve, WIDE), exc, pages.append)
    d = records.concat_pages(pages)
    return exc, d


ROUGH = noise.NoiseSources(DELTA, 0.002)


@pytest.mark.parametrize("B,w0", [(0.0, 60.0), (0.5, 250.0), (1.0, 125.0), (2.0, 500.0),
                                  (2.0, 60.0)])
def test_prediction_holds_the_rough_simulators_command(B, w0):
    """The goal: predicted force-noise RMS (10-500 Hz) within 10 % of the rough simulator's
    recorded command (0.5 N white excitation, 120 s). Measured within 0.4 % over the grid
    w0 = 60-500 rad/s, B = 0-2 N s/m; the measurement's own 95 % interval is ~ +-0.6 %, so
    the prediction must lie within it widened by 2 % (the white model's own approximations)."""
    ve = sd(B, w0)
    exc, d = rough_run(ve, 0.5, seed=11)
    m = force_noise.measure(d["command"], exc, ve.T, BAND)
    pred = noise.force_noise(PLANT, ve, ROUGH, BAND).rms_command
    assert abs(m.rms_n / pred - 1) < 0.10
    assert m.ci95[0] / 1.02 <= pred <= m.ci95[1] * 1.02


def test_slow_motion_needs_the_coloured_error_and_the_flag_says_so():
    """0.03 N of excitation moves the handle ~0.2 steps a sample: the white model is 31 % high
    on B = 2, w0 = 500 (measured); the model of the stated motion's error (its increments
    from the same loop) within 10 %, and it flags the white model's condition as failed.
    Both ways: at 0.5 N the flag stays white and the two models agree."""
    ve = sd(2.0, 500.0)
    exc, d = rough_run(ve, 0.03, seed=4)
    m = force_noise.measure(d["command"], exc, ve.T, BAND)
    white = noise.force_noise(PLANT, ve, ROUGH, BAND)
    inc = noise.increments_from_excitation(PLANT, ve, 0.03)
    coloured = noise.force_noise(PLANT, ve, ROUGH, BAND, increments=inc)
    assert m.rms_n / white.rms_command < 0.8  # the white model fails here
    assert abs(m.rms_n / coloured.rms_command - 1) < 0.10
    assert not coloured.white and coloured.rho1 > 0.5
    fast = noise.force_noise(PLANT, ve, ROUGH, BAND,
                             increments=noise.increments_from_excitation(PLANT, ve, 0.5))
    assert fast.white and fast.rms_command == pytest.approx(white.rms_command, rel=1e-3)


@pytest.mark.parametrize("ve", [sd(1.0, 125.0), sd(0.0, 60.0), sd(2.0, 500.0, td=0.002),
                                VirtualEnvironment("damper", B=1.0, w0=250.0)], ids=str)
def test_the_increments_of_an_excited_loop_are_exact(ve):
    """Truth: x = h * f with h the exact sampled loop's impulse response (dlsim of
    ``closed_loop``, which the simulator equals to rounding: tests/test_loop.py), so
    D_j = std^2 sum_i (h[i + j] - h[i])^2 (h = 0 before 0); a damper's h tends to a constant
    (any offset is at rest) and its increments still converge."""
    n = 40_000
    impulse = np.zeros(n)
    impulse[0] = 1.0
    _, y, _ = signal.dlsim(linear.closed_loop(PLANT, ve).as_dlti(), impulse)
    h = np.concatenate([np.zeros(30), y[:, 0]])
    D = noise.increments_from_excitation(PLANT, ve, 0.5)
    for j in (1, 2, 5, 20):
        truth = 0.25 * np.sum((h[j:] - h[:-j]) ** 2)
        assert D[j - 1] == pytest.approx(truth, rel=1e-6)


# ------------------------------------------------------------------- Coulomb friction's part
def test_sign_remnant_is_the_arcsine_law_of_a_gaussian_velocity():
    """Truth: a Gaussian AR(2) velocity (a resonance, as the loop's) of known spectrum, its
    d = Fc sign(v) - b_eq v counted over 2^20 samples (b_eq = Fc E|v| / E v^2 from the draw):
    d's variance is Fc^2 (1 - 2/pi) exactly, and its power in four bands within 3 % of the
    arcsine law's (Welch's estimate, 64 segments: ~1 % std in the lowest band)."""
    T, fc, n = 0.001, 0.02, 1 << 20
    a = [1.0, -1.9, 0.93]  # poles at |z| 0.964, ~25 Hz
    f = np.linspace(0.0, 0.5 / T, 4097)
    _, h = signal.freqz([1.0], a, worN=f, fs=1 / T)
    Sv = 2 * T * np.abs(h) ** 2  # unit white input
    Sd, sigma = noise.sign_remnant(f, Sv, fc, T)
    v = signal.lfilter([1.0], a, np.random.default_rng(2).normal(0.0, 1.0, n))[1000:]
    assert sigma == pytest.approx(np.std(v), rel=0.02)
    d = fc * np.sign(v) - fc * np.mean(np.abs(v)) / np.mean(v**2) * v
    assert np.trapezoid(Sd, f) == pytest.approx(fc**2 * (1 - 2 / math.pi), rel=1e-3)
    fw, Pw = signal.welch(d, fs=1 / T, nperseg=16384)  # 0.06 Hz: no leakage at 1 Hz
    for lo, hi in ((1.0, 10.0), (10.0, 50.0), (50.0, 200.0), (200.0, 500.0)):
        sel, selw = (f >= lo) & (f < hi), (fw >= lo) & (fw < hi)
        assert np.trapezoid(Pw[selw], fw[selw]) == pytest.approx(np.trapezoid(Sd[sel], f[sel]),
                                                                 rel=0.03)


@pytest.mark.parametrize("fc,B,w0,allow", [(0.01, 0.0, 60.0, 0.03), (0.02, 0.0, 60.0, 0.03),
                                           (0.02, 1.0, 60.0, 0.03), (0.05, 2.0, 125.0, 0.08)])
def test_friction_aware_prediction_holds_the_rough_simulator_with_friction(fc, B, w0, allow):
    """Issue 45's goal on issue 41's rough simulator (Coulomb friction, the encoder step, 2 mN):
    predicted command noise within 10 % of the record's (0.5 N white, 120 s). The linear
    model misses these by 14-43 % (measured); the friction-aware one lies within the
    measurement's 95 % interval widened by ``allow``: the Gaussian velocity's own error,
    measured up to 2.1 % for Fc <= 0.02 N and 7 % at 0.05 N (docs/design.md)."""
    ve = sd(B, w0)
    exc, d = rough_run(ve, 0.5, seed=11, coulomb_n=fc)
    m = force_noise.measure(d["command"], exc, ve.T, BAND)
    src = noise.NoiseSources(DELTA, 0.002, fc)
    pred = noise.force_noise(PLANT, ve, src, BAND, excitation=noise.Excitation(0.5))
    linear_only = noise.force_noise(PLANT, ve, ROUGH, BAND).rms_command
    assert m.rms_n / linear_only - 1 > 0.10  # the gap this closes
    assert abs(m.rms_n / pred.rms_command - 1) < 0.10
    assert m.ci95[0] / (1 + allow) <= pred.rms_command <= m.ci95[1] * (1 + allow)
    assert pred.friction.gaussian and pred.parts["friction"] > 0


def test_the_stick_share_flags_where_the_velocity_is_not_gaussian():
    """Both ways on the rough simulator, B = 1, w0 = 125: at 0.05 N of excitation and
    Fc = 0.05 N the handle rests ~60 % of the time (measured); the model, 29 % off there,
    says its condition fails (stick share far above STICK_SHARE_MAX); at 0.5 N and 0.02 N it
    holds within 3 % and the flag stays clear (no false alarm)."""
    ve = sd(1.0, 125.0)
    for std, fc, holds in ((0.05, 0.05, False), (0.5, 0.02, True)):
        exc, d = rough_run(ve, std, seed=11, coulomb_n=fc)
        m = force_noise.measure(d["command"], exc, ve.T, BAND)
        pred = noise.force_noise(PLANT, ve, noise.NoiseSources(DELTA, 0.002, fc), BAND,
                                 excitation=noise.Excitation(std))
        assert pred.friction.gaussian is holds
        assert (abs(m.rms_n / pred.rms_command - 1) < 0.03) is holds
    assert pred.friction.stick_share < noise.STICK_SHARE_MAX / 10


def test_friction_needs_a_motion_and_says_when_it_holds_the_handle():
    ve = sd(1.0, 125.0)
    src = noise.NoiseSources(DELTA, 0.0, 0.05)
    with pytest.raises(UserError, match="excitation"):
        noise.force_noise(PLANT, ve, src, BAND)
    with pytest.raises(UserError, match="holds the handle"):  # Fc sqrt(2/pi) above 0.01 N
        noise.force_noise(PLANT, ve, src, BAND, excitation=noise.Excitation(0.01))
    with pytest.raises(UserError, match="excitation std"):
        noise.Excitation(0.0)
    with pytest.raises(UserError, match="coulomb_n"):
        noise.NoiseSources(0.0, 0.0, -0.1)


# ------------------------------------------------------------------------- the estimator
def synthetic(seed, n=16_384, noise_std=0.01):
    """A lightly damped loop's response (a 2 s ring-down at T = 1 ms: leakage for any short
    segment) to white force, plus coloured noise of known spectrum: truth for the estimator."""
    rng = np.random.default_rng(seed)
    f = rng.normal(0, 1.0, n)
    b, a = signal.cheby1(2, 1, [0.004, 0.006], "bandpass")  # a resonance near 2.5 Hz
    u = signal.lfilter(b, a, f) + f
    nb, na = [1.0, 0.5], [1.0, -0.3]
    v = signal.lfilter(nb, na, rng.normal(0, noise_std, n))
    return u + v, f, (nb, na, noise_std)


def true_rms(coefs, T, band):
    nb, na, std = coefs
    fr, h = signal.freqz(nb, na, worN=200_000, fs=1 / T)
    sel = (fr >= band[0]) & (fr <= band[1])
    return math.sqrt(np.trapezoid(2 * T * std**2 * np.abs(h[sel]) ** 2, fr[sel]))


def test_estimator_intervals_cover_the_truth():
    """200 records of 16 s: the 95 % interval holds the true band RMS in 95 % of them
    (binomial 95 % range for 200 draws: 183-196), and the estimate is unbiased to 0.3 %."""
    T, band = 0.001, (10.0, 400.0)
    truth = None
    hits, ratios = 0, []
    for seed in range(200):
        u, f, coefs = synthetic(seed)
        truth = truth or true_rms(coefs, T, band)
        m = force_noise.measure(u, f, T, band)
        hits += m.ci95[0] <= truth <= m.ci95[1]
        ratios.append(m.rms_n / truth)
    assert 183 <= hits <= 198
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.003)


def test_estimator_outside_the_excited_band_fits_the_transient_only():
    """Excitation limited to 0-5 Hz: above it the command is noise alone; the windows there fit
    no H and still read the noise's level."""
    T, band, n = 0.001, (20.0, 400.0), 32_768
    rng = np.random.default_rng(3)
    b, a = signal.butter(8, 5.0, fs=1 / T)
    f = signal.lfilter(b, a, rng.normal(0, 1.0, n))
    v = rng.normal(0, 0.01, n)
    m = force_noise.measure(f * 2 + v, f, T, band)
    truth = 0.01 * math.sqrt(2 * T * (band[1] - band[0]))
    assert m.ci95[0] <= truth <= m.ci95[1]


@pytest.mark.parametrize("args,match", [
    ((np.zeros(100), np.zeros(100), 0.001, BAND), "at least"),
    ((np.zeros(1000), np.zeros(999), 0.001, BAND), "same length"),
    ((np.full(1000, np.nan), np.zeros(1000), 0.001, BAND), "finite"),
    ((np.zeros(1000), np.zeros(1000), 0.001, (300.0, 100.0)), "band"),
    ((np.zeros(1000), np.zeros(1000), 0.001, (499.99, 500.0)), "too few"),
])
def test_estimator_refuses_bad_input_in_one_line(args, match):
    with pytest.raises(UserError, match=match):
        force_noise.measure(*args)


def test_model_refuses_bad_sources_and_bands():
    with pytest.raises(UserError, match="quantum_m"):
        noise.NoiseSources(-1.0)
    with pytest.raises(UserError, match="force_noise_n"):
        noise.NoiseSources(0.0, float("nan"))
    with pytest.raises(UserError, match="band"):
        noise.force_noise(PLANT, sd(1.0, 125.0), ROUGH, (100.0, 10.0))
