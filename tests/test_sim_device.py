"""Simulated device: exact plant, friction against an event-located ODE solution, options."""
import math
import time

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from labbench.device import DeviceFault, Sample
from labbench.registry import open_device
from labbench.errors import UserError
from labbench.protocols.excitation import white_noise
from labbench.rig import Rig, rig_from_dict
from labbench.sim_backend.sim_device import ESTOP_LATCHED, open_sim

M, B, T = 0.094, 0.10, 0.001


def drive(dev, forces):
    """Positions x[0..len(forces)] (true, unquantised) with forces[k] held over step k."""
    dev.enable()
    xs = [dev.read_raw(1.0)[2]]
    for u in forces:
        dev.command(u)
        xs.append(dev.read_raw(1.0)[2])
    return np.array(xs)


def test_open_loop_step_matches_analytic_solution():
    # m x'' + b x' = F from rest: x(t) = F/b (t - tau (1 - exp(-t/tau))), tau = m/b
    F, n = 0.3, 500
    x = drive(open_sim(Rig()), [F] * n)
    t = np.arange(n + 1) * T
    tau = M / B
    exact = F / B * (t - tau * (1 - np.exp(-t / tau)))
    np.testing.assert_allclose(x, exact, rtol=1e-11, atol=1e-16)


def coulomb_truth(x0, v0, u, fc, t_end, m=M, b=B):
    """Reference: m v' = u - b v - fc sign(v), sticking while |u| <= fc; ODE solver with events."""
    t, x, v = 0.0, x0, v0
    while t < t_end - 1e-15:
        if v == 0.0:
            if abs(u) <= fc:
                return x, 0.0
            s = math.copysign(1.0, u)
        else:
            s = math.copysign(1.0, v)

        def rhs(_, y, s=s):
            return [y[1], (u - b * y[1] - fc * s) / m]

        def stop(_, y):
            return y[1]

        stop.terminal, stop.direction = True, -s
        sol = solve_ivp(rhs, (t, t_end), [x, v], events=stop, rtol=1e-12, atol=1e-15,
                        method="DOP853")
        x, v = sol.y[0, -1], sol.y[1, -1]
        if sol.status == 1:  # velocity reached zero
            t = sol.t_events[0][0]
            x, v = sol.y_events[0][0][0], 0.0
        else:
            t = t_end
    return x, v


@pytest.mark.parametrize("v0,u,end", [
    (0.01, 0.0, "rest"), (0.01, 0.03, "rest"), (-0.04, 0.5, "reversed"), (0.02, -0.3, "reversed"),
    (0.0, 0.02, "rest"), (0.0, 0.2, "moving"), (0.0, -0.2, "moving")])
def test_coulomb_step_matches_event_located_ode(v0, u, end):
    fc = 0.05
    dev = open_sim(Rig(), coulomb_n=fc, v0_m_s=v0)
    dev.enable()
    dev.read_raw(1.0)
    x_ref, v_ref = 0.0, v0
    for _ in range(80):  # several steps: slide, reach zero inside a step, stick or slide on
        dev.command(u)
        dev.read_raw(1.0)
        x_ref, v_ref = coulomb_truth(x_ref, v_ref, u, fc, T)
        assert dev.x == pytest.approx(x_ref, rel=1e-8, abs=1e-12)
        assert dev.v == pytest.approx(v_ref, rel=1e-7, abs=1e-10)
    if end == "rest":
        assert dev.v == 0.0
    elif end == "reversed":
        assert dev.v * v0 < 0
    else:
        assert dev.v * u > 0


def test_coulomb_friction_sticks_below_breakaway_and_never_adds_energy():
    dev = open_sim(Rig(), coulomb_n=0.05)
    x = drive(dev, [0.049] * 200)
    assert np.all(x == 0.0)
    dev = open_sim(Rig(), coulomb_n=0.05, v0_m_s=0.1)
    dev.enable()
    dev.read_raw(1.0)
    speeds = []
    for _ in range(300):
        dev.read_raw(1.0)
        speeds.append(abs(dev.v))
    assert np.all(np.diff(speeds) <= 0.0)
    assert speeds[-1] == 0.0  # came to rest and stays


def test_quantisation_reports_whole_counts_within_half_a_count():
    rig = Rig()
    q = rig.metres_per_count
    dev = open_sim(rig, quantize=True)
    dev.enable()
    for u in np.sin(np.arange(300) * 0.05) * 0.5:
        dev.command(float(u))
        _, _, x, _ = dev.read_raw(1.0)
        counts = x / q
        assert counts == pytest.approx(round(counts), abs=1e-6)
        assert abs(x - dev.x) <= q / 2 * (1 + 1e-9)


def test_force_noise_has_the_set_std_and_is_reproducible():
    def applied(seed):
        dev = open_sim(Rig(), force_noise_n=0.2, seed=seed)
        dev.enable()
        dev.read_raw(1.0)
        out = []
        for _ in range(20000):
            dev.command(0.1)
            dev.read_raw(1.0)
            out.append(dev.applied_n)
        return np.array(out)

    a, b = applied(3), applied(3)
    np.testing.assert_array_equal(a, b)
    assert np.std(a - 0.1) == pytest.approx(0.2, rel=0.03)  # std error of a std ~0.5 %
    assert np.mean(a - 0.1) == pytest.approx(0.0, abs=5 * 0.2 / math.sqrt(20000))
    assert not np.array_equal(a, applied(4))
    # The run's seed also seeds the protocol's white noise: the two must be independent
    # (correlation of 20 000 independent samples: std 0.007; a shared stream gives 1).
    exc = white_noise(20000, 0.001, 0.5, seed=3)
    assert abs(np.corrcoef(a - 0.1, exc)[0, 1]) < 0.05


def test_extra_delay_shifts_the_response_by_whole_samples():
    forces = [0.0] * 3 + [1.0] + [0.0] * 30
    base = drive(open_sim(Rig()), forces)
    late = drive(open_sim(Rig(), extra_delay_samples=4), forces)
    np.testing.assert_array_equal(late[4:], base[:-4])
    assert np.all(late[:8] == 0.0)


def test_realtime_pacing_holds_the_sample_period():
    dev = open_sim(Rig(), realtime=True)
    t0 = time.perf_counter()
    for _ in range(60):
        dev.read_raw(1.0)
    assert time.perf_counter() - t0 >= 59 * T  # never early (lateness is not asserted)
    assert dev.describe().details["paced"] is True


def test_realtime_pacing_restarts_after_idle_instead_of_catching_up():
    # Open, read a little, sit idle (connected, run not started yet), then read on: the
    # idle time is not a backlog. Caught up, the first idle_s / T reads would come at once.
    idle_s = 0.3
    dev = open_sim(Rig(), realtime=True)
    for _ in range(5):
        dev.read_raw(1.0)
    time.sleep(idle_s)
    n = 200  # under idle_s / T = 300: with catch-up every one of them would be immediate
    t0 = time.perf_counter()
    for _ in range(n):
        dev.read_raw(1.0)
    assert time.perf_counter() - t0 >= 0.7 * n * T  # lateness (a noisy machine) not asserted
    dev.enable()  # a second pause, after enable as in a run: paced again from the next read
    time.sleep(idle_s)
    t0 = time.perf_counter()
    for _ in range(n):
        dev.read_raw(1.0)
    assert time.perf_counter() - t0 >= 0.7 * n * T


def test_disabled_and_emergency_stopped_device_applies_no_force():
    dev = open_sim(Rig())
    dev.read_raw(1.0)
    dev.command(1.0)
    dev.read_raw(1.0)
    assert dev.applied_n == 0.0  # never enabled
    dev.enable()
    dev.command(1.0)
    dev.read_raw(1.0)
    assert dev.applied_n == 1.0
    dev.emergency_stop()
    dev.command(1.0)  # a late command from the loop thread is ignored
    assert dev.read_raw(1.0)[3] == ESTOP_LATCHED  # and the samples say so
    assert dev.applied_n == 0.0
    with pytest.raises(DeviceFault):
        dev.enable()
    dev.close()
    dev.close()
    with pytest.raises(DeviceFault):
        dev.read(1.0)


def test_read_returns_sample_with_timing_of_the_sampled_model():
    with open_device("sim", Rig()) as dev:
        s0, s1 = dev.read(1.0), dev.read(1.0)
    assert isinstance(s0, Sample)
    assert (s0.seq, s0.t_s, s1.seq, s1.t_s) == (0, 0.0, 1, T)


@pytest.mark.parametrize("table,field", [
    ({"m": 0}, "m"), ({"b": -1}, "b"), ({"coulomb_n": "x"}, "coulomb_n"),
    ({"quantize": 1}, "quantize"), ({"extra_delay_samples": 1.5}, "extra_delay_samples"),
    ({"force_noise_n": float("nan")}, "force_noise_n"), ({"mass": 1.0}, "mass"),
])
def test_bad_sim_settings_give_one_clear_error(table, field):
    rig = rig_from_dict({"sim": table}, source="bench.toml")
    with pytest.raises(UserError) as err:
        open_sim(rig)
    msg = str(err.value)
    assert "bench.toml" in msg and "[sim]" in msg and field in msg and "\n" not in msg
    with pytest.raises(UserError, match=field):
        open_sim(Rig(), **table)


def test_keyword_options_override_the_rig_table():
    rig = rig_from_dict({"sim": {"m": 0.2, "b": 0.3}})
    d = open_sim(rig, b=0.5).describe().details
    assert (d["m"], d["b"]) == (0.2, 0.5)
