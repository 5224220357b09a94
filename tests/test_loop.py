"""The loop chain on the simulator against the exact sampled model (labbench.model.linear)."""
import threading
import time

import numpy as np
import pytest
from scipy import signal

from labbench import records
from labbench.errors import UserError
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.rig import Rig
from labbench.model.linear import closed_loop, z_sampled
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.sim_backend.sim_device import open_sim

PLANT = Plant(0.094, 0.10)
# Limits far outside these runs, so the envelope never acts and the loop is the bare model.
WIDE = SafetyConfig(force_limit_n=1e3, force_rate_limit_n_per_s=1e9, velocity_limit_m_s=1e3,
                    position_limits_m=(-1e3, 1e3), energy_limit_j=1e3, watchdog_s=1.0,
                    enable_force_threshold_n=1e-12)

VES = [
    VirtualEnvironment("none"),
    VirtualEnvironment("spring", K=50.0),
    VirtualEnvironment("damper", B=1.0, td=0.001),
    VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0),
    VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.002),
    VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, td=0.005),
]


def noise(n, std=0.5, seed=0):
    f = np.random.default_rng(seed).normal(0.0, std, n)
    f[0] = 0.0  # the enable gate opens at the first sample
    return f


def run(ve, exc, safety=WIDE, device=None, **kw):
    pages = []
    device = device or open_sim(Rig(), m=PLANT.m, b=PLANT.b)
    out = run_loop(device, HapticLoop(ve, safety), exc, pages.append, **kw)
    return out, pages, records.concat_pages(pages)


@pytest.mark.parametrize("ve", VES, ids=lambda v: f"{v.kind}-td{v.td}")
def test_sim_run_equals_the_exact_sampled_model(ve):
    exc = noise(5000)
    out, _, data = run(ve, exc)
    assert out.status == "completed" and out.n_done == len(exc)
    _, y, _ = signal.dlsim(closed_loop(PLANT, ve).as_dlti(), exc)
    scale = np.max(np.abs(y))
    assert scale > 1e-3  # the run moved the handle
    np.testing.assert_allclose(data["position"], y[:, 0], rtol=0, atol=1e-9 * scale)
    np.testing.assert_array_equal(data["excitation"], exc)
    assert np.all(data["flags"] == 0)


@pytest.mark.parametrize("ve", VES[1:], ids=lambda v: f"{v.kind}-td{v.td}")
def test_recorded_channels_are_the_difference_equations(ve):
    exc = noise(3000, seed=1)
    _, _, d = run(ve, exc)
    x, T, a = d["position"], ve.T, ve.filter_pole
    dx = np.diff(x, prepend=0.0)
    v = signal.lfilter([(1 - a) / T], [1, -a], dx)  # v[k] = a v[k-1] + (1-a) dx / T
    np.testing.assert_allclose(d["velocity"], v, rtol=1e-9, atol=1e-12)
    f = ve.K * x + ve.B * v
    np.testing.assert_allclose(d["ve_force"], f, rtol=1e-9, atol=1e-12)
    n = ve.delay_samples
    f_late = np.concatenate([np.zeros(n), f[:len(f) - n]])
    np.testing.assert_allclose(d["command"], exc - f_late, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(d["t"], np.arange(len(exc)) * T)
    np.testing.assert_array_equal(d["seq"], np.arange(len(exc)))


def test_white_noise_run_converges_to_the_sampled_impedance():
    # 2 minutes at 1 kHz, K = 50, B = 1, w0 = 125 (the paper's experiment): an averaged
    # cross-spectral estimate of Z = F / (jw X) approaches the exact sampled Z.
    ve = VES[3]
    exc = noise(120_000, std=1.0, seed=2)
    _, _, d = run(ve, exc)
    fs = 1 / ve.T
    w_hz, Pff = signal.welch(exc, fs, nperseg=4096)
    _, Pfx = signal.csd(exc, d["position"], fs, nperseg=4096)
    w = 2 * np.pi * w_hz
    band = (w >= 2) & (w <= 100)
    Z = Pff[band] / (1j * w[band] * Pfx[band])  # H1 estimate of X/F, inverted
    Zt = z_sampled(PLANT, ve, w[band])
    assert np.max(np.abs(Z - Zt) / np.abs(Zt)) < 0.05


def test_step_and_advance_agree_and_state_is_readable():
    ve = VES[4]
    loop_a, loop_b = HapticLoop(ve, WIDE), HapticLoop(ve, WIDE)
    for k, (x, f) in enumerate(zip(np.linspace(0, 0.01, 50), noise(50))):
        row = loop_a.advance(k, k * ve.T, x, f)
        assert loop_b.step(k, k * ve.T, x, f) == row[6]
        assert (loop_b.velocity, loop_b.ve_force, loop_b.excitation, loop_b.flags) == row[3:6] + (row[7],)
    with pytest.raises(AttributeError):
        _ = loop_a.no_such_thing


def test_recorded_run_replays_through_a_fresh_chain_bit_for_bit():
    # Saturations and the gate included: the chain is a pure function of (x, f_exo).
    ve = VES[4]
    exc = noise(2000, std=2.0, seed=4)
    exc[0] = 1.0  # gate opens a few samples late
    cfg = SafetyConfig(force_limit_n=3.0, force_rate_limit_n_per_s=3000.0)
    _, _, d = run(ve, exc, safety=cfg)
    assert np.any(d["flags"] & 1) and np.any(d["flags"] & 2) and d["flags"][0] & 4
    fresh = HapticLoop(ve, cfg)
    rows = [fresh.advance(int(s), t, x, f) for s, t, x, f in zip(d["seq"], d["t"], d["position"], exc)]
    for c, name in enumerate(records.CHANNELS):
        np.testing.assert_array_equal(np.array([r[c] for r in rows]), d[name])


class ReadOnly:
    """A device offering only the Device protocol's read() (no read_raw fast path)."""

    def __init__(self, dev):
        self._dev = dev

    def __getattr__(self, name):
        if name == "read_raw":
            raise AttributeError(name)
        return getattr(self._dev, name)


def test_plain_read_path_gives_the_same_run():
    ve, exc = VES[4], noise(700, seed=3)
    _, _, fast = run(ve, exc)
    _, _, plain = run(ve, exc, device=ReadOnly(open_sim(Rig(), m=PLANT.m, b=PLANT.b)))
    for name in records.CHANNELS:
        np.testing.assert_array_equal(fast[name], plain[name])


def test_pages_are_numbered_sized_and_reported():
    seen = []
    out, pages, data = run(VES[1], noise(1050), page_size=100, first_page=7,
                           progress=lambda done, total: seen.append((done, total)))
    kinds = [p["kind"] for p in pages]
    page_recs = [p for p in pages if p["kind"] == records.PAGE]
    assert [p["index"] for p in page_recs] == list(range(7, 18))
    assert [len(p["data"]["t"]) for p in page_recs] == [100] * 10 + [50]
    assert seen[-1] == (1050, 1050) and len(seen) == 11
    assert kinds.count(records.EVENT) == 1  # "enabled"
    assert out.stats["pages"] == 11
    assert data["seq"].dtype == np.int64 and data["flags"].dtype == np.int64


def test_timing_is_measured_and_returned():
    out, _, _ = run(VES[1], noise(2000))
    t = out.timing
    assert 0 < t["p50_s"] <= t["p99_s"] <= t["max_s"]
    assert t["paced"] is False and t["overruns"] == 0 and t["wall_s"] > 0


def test_sample_time_mismatch_is_a_user_error():
    with pytest.raises(UserError, match="sample time"):
        run(VirtualEnvironment("spring", K=1.0, T=0.002), noise(10))


def test_stop_and_emergency_stop_from_another_thread_zero_force_at_once():
    dev = open_sim(Rig(), realtime=True)
    stop = threading.Event()
    results = {}

    def worker():
        results["out"], results["pages"], results["data"] = run(
            VES[1], np.full(5000, 0.1), safety=SafetyConfig(), device=dev, stop=stop)

    th = threading.Thread(target=worker)
    th.start()
    time.sleep(0.15)
    dev.emergency_stop()  # the GUI's E-STOP: force off at the device now ...
    assert dev.estopped and dev._active is False
    stop.set()  # ... and the loop ends at its next sample
    th.join(timeout=5.0)
    assert not th.is_alive()
    out = results["out"]
    assert out.status == "aborted" and 0 < out.n_done < 5000
    assert dev.applied_n == 0.0
    events = [p for p in results["pages"] if p["kind"] == records.EVENT]
    assert events[-1]["name"] == "stop"


def test_ctrl_c_ends_the_loop_like_stop_and_keeps_the_samples():
    dev = open_sim(Rig())
    real_read = dev.read_raw

    def read_raw(timeout):
        if real_read.__self__._k == 249:
            raise KeyboardInterrupt
        return real_read(timeout)

    dev.read_raw = read_raw
    out, pages, data = run(VES[1], noise(1000), device=dev)
    assert out.status == "aborted" and "Ctrl-C" in out.reason and out.n_done == 250
    assert len(data["t"]) == 250 and dev._u == 0.0 and dev.enabled is False
    assert pages[-1]["kind"] == records.EVENT and pages[-1]["name"] == "stop"
