"""Simulated device: exact plant, friction against an event-located ODE solution, options."""
import math
import time

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from labbench.device import DeviceFault, Sample
from labbench.registry import open_device
from labbench.errors import UserError
from labbench.model.linear import latency_inputs, zoh_matrices
from labbench.protocols.excitation import white_noise
from labbench.rig import Rig, rig_from_dict
from labbench.sim_backend.sim_device import ESTOP_LATCHED, open_sim
from labbench.model.ve import Plant

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


def coulomb_truth(x0, v0, u, fc, t_end, m=M, b=B, cog=None):
    """Reference: m v' = u - b v - fc sign(v) - A sin(k x) (``cog`` = (A, k), else no
    detents), sticking while |u - A sin(k x)| <= fc; ODE solver with events (a stop of the
    velocity, and a start from rest when the detent's force grows past fc)."""
    A, kc = cog if cog else (0.0, 0.0)

    def cogging(x):
        return A * math.sin(kc * x)

    t, x, v = 0.0, x0, v0
    while t < t_end - 1e-15:
        if v == 0.0:
            if abs(u - cogging(x)) <= fc:
                return x, 0.0  # x does not move, so neither does the detent's force
            s = math.copysign(1.0, u - cogging(x))
        else:
            s = math.copysign(1.0, v)

        def rhs(_, y, s=s):
            return [y[1], (u - b * y[1] - fc * s - cogging(y[0])) / m]

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
    with pytest.raises(UserError) as err:  # when the rig file is read, before any device opens
        rig_from_dict({"sim": table}, source="bench.toml")
    msg = str(err.value)
    assert "bench.toml" in msg and "[sim]" in msg and field in msg and "\n" not in msg
    with pytest.raises(UserError, match=field):
        open_sim(Rig(), **table)


def test_keyword_options_override_the_rig_table():
    rig = rig_from_dict({"sim": {"m": 0.2, "b": 0.3}})
    d = open_sim(rig, b=0.5).describe().details
    assert (d["m"], d["b"]) == (0.2, 0.5)


def _delayed_truth(x, v, u_prev, u, fc, alpha, cog=None):
    """The reference over one step of a device with a fractional delay: the previous command
    for the first alpha T, this one for the rest."""
    x, v = coulomb_truth(x, v, u_prev, fc, alpha * T, cog=cog)
    return coulomb_truth(x, v, u, fc, (1 - alpha) * T, cog=cog)


@pytest.mark.parametrize("alpha,whole", [(0.3, 0), (0.75, 0), (0.5, 2)])
def test_coulomb_friction_with_a_fractional_delay_matches_event_located_ode(alpha, whole):
    # forces of 2x fc std: the handle sticks, slides, reverses inside either stretch of a step
    fc = 0.05
    forces = np.random.default_rng(7).normal(0.0, 2 * fc, 300)
    dev = open_sim(Rig(), coulomb_n=fc, extra_delay_fraction=alpha, extra_delay_samples=whole,
                   v0_m_s=0.02)
    dev.enable()
    dev.read_raw(1.0)
    x, v, applied = 0.0, 0.02, [0.0] * (whole + 1)  # commands in flight, oldest first
    stuck = reversed_ = 0
    for u in forces:
        dev.command(float(u))
        dev.read_raw(1.0)
        applied.append(float(u))
        v_before = v
        x, v = _delayed_truth(x, v, applied[-whole - 2], applied[-whole - 1], fc, alpha)
        stuck += v == 0.0
        reversed_ += v * v_before < 0
        assert dev.x == pytest.approx(x, rel=1e-8, abs=1e-12)
        assert dev.v == pytest.approx(v, rel=1e-7, abs=1e-10)
    assert stuck > 10 and reversed_ > 10  # the sequence did exercise both


def test_friction_with_a_delay_reduces_to_the_linear_latency_model_while_sliding_one_way():
    # A handle that never stops feels friction as a constant force -fc: the run is the
    # exact linear latency model (labbench.model.linear) driven with every force lowered by
    # fc, the command before the first one (0) included.
    fc, alpha = 0.05, 0.4
    forces = 0.3 + 0.1 * np.sin(np.arange(400) * 0.03)
    x = drive(open_sim(Rig(), coulomb_n=fc, extra_delay_fraction=alpha, v0_m_s=0.1), forces)
    Ad, _ = zoh_matrices(M, B, T)
    g_late, g_early = latency_inputs(Plant(M, B), T, alpha)
    s, prev, ref = np.array([0.0, 0.1]), 0.0, [0.0]
    for u in forces:
        s = Ad @ s + g_late * (u - fc) + g_early * (prev - fc)
        prev = u
        ref.append(s[0])
    np.testing.assert_allclose(x, ref, rtol=1e-10, atol=1e-15)


def test_a_stuck_handle_with_a_delay_stays_put_under_forces_below_breakaway():
    fc = 0.05
    forces = 0.049 * np.sign(np.sin(np.arange(300) * 0.7))  # switching within |u| < fc
    x = drive(open_sim(Rig(), coulomb_n=fc, extra_delay_fraction=0.6, extra_delay_samples=1),
              forces)
    assert np.all(x == 0.0)


COG_A, COG_P = 0.03, 0.004  # N, m: detents 4 mm apart at the handle, 30 mN deep


@pytest.mark.parametrize("fc,v0,alpha", [(0.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.02, 0.05, 0.0),
                                         (0.02, 0.0, 0.5)])
def test_cogging_matches_an_ode_solution(fc, v0, alpha):
    # 300 steps from a point off a detent, under a slow force that drags it over detents.
    # The substeps hold the detent's force (second order: ~1e-9 m a step sliding); a stop
    # inside a substep is decided on the force at its predicted midpoint, which can keep
    # the handle stuck up to one substep too long: measured worst 1.4e-7 m over these
    # runs. Held to 1 % of an encoder count (what any reading of the rig could notice).
    cog = (COG_A, 2 * math.pi / COG_P)
    count = Rig().metres_per_count
    dev = open_sim(Rig(), coulomb_n=fc, cogging_n=COG_A, cogging_period_m=COG_P, v0_m_s=v0,
                   x0_m=0.0007, extra_delay_fraction=alpha)
    dev.enable()
    dev.read_raw(1.0)
    x, v, prev = 0.0007, v0, 0.0
    for k in range(300):
        u = 0.06 * math.sin(k * 0.05)
        dev.command(u)
        dev.read_raw(1.0)
        x, v = _delayed_truth(x, v, prev, u, fc, alpha, cog)
        prev = u
        assert dev.x == pytest.approx(x, abs=0.01 * count)
        assert dev.v == pytest.approx(v, abs=0.01 * count / T)


def test_cogging_alone_conserves_energy():
    # no damping, friction or force: 1/2 m v^2 + (A / k)(1 - cos k x) is constant; the
    # handle rolls over the detents (its energy is above their 2 A / k barrier)
    k = 2 * math.pi / COG_P
    dev = open_sim(Rig(), b=0.0, cogging_n=COG_A, cogging_period_m=COG_P, v0_m_s=0.1)
    dev.enable()
    dev.read_raw(1.0)

    def energy():
        return 0.5 * M * dev.v**2 + COG_A / k * (1 - math.cos(k * dev.x))

    # The substeps' second-order error makes the energy wobble as the handle rolls over
    # each detent (measured 5.0e-6 of it, the same in every second of a 20 s run): bounded,
    # no drift. Held to 1e-5, and the second second's wobble no larger than the first's.
    e0 = energy()
    assert e0 > 2 * COG_A / k
    wobble = []
    for _ in range(2):
        worst = 0.0
        for _ in range(1000):
            dev.read_raw(1.0)
            worst = max(worst, abs(energy() - e0))
        wobble.append(worst)
    assert dev.x > 10 * COG_P  # it crossed detents
    assert max(wobble) < 1e-5 * e0
    assert wobble[1] < 1.1 * wobble[0]


def test_cogging_settles_in_the_detent_the_force_predicts():
    # with damping and a constant force u < A the handle comes to rest where the detent
    # balances it: A sin(k x) = u; with friction anywhere |u - A sin(k x)| <= fc
    k = 2 * math.pi / COG_P
    u = 0.6 * COG_A
    x = drive(open_sim(Rig(), b=2.0, cogging_n=COG_A, cogging_period_m=COG_P), [u] * 3000)
    assert x[-1] == pytest.approx(math.asin(u / COG_A) / k, abs=1e-9)
    fc = 0.005
    dev = open_sim(Rig(), b=0.5, coulomb_n=fc, cogging_n=COG_A, cogging_period_m=COG_P,
                   v0_m_s=0.02)
    x = drive(dev, [u] * 3000)
    assert dev.v == 0.0 and x[-1] == x[-200]  # at rest, and stays there
    assert abs(u - COG_A * math.sin(k * x[-1])) <= fc
    assert abs(x[-1] - math.asin(u / COG_A) / k) < COG_P / 4  # in the first detent


def test_cogging_holds_a_handle_at_rest_exactly_and_lets_it_go_past_breakaway():
    # at rest a quarter of a detent off its bottom the detent pushes back with A; a force
    # that leaves less than fc unbalanced keeps it there, exactly; a little more moves it
    fc = 0.01
    x0 = COG_P / 4
    for u, moves in ((COG_A - 0.99 * fc, False), (COG_A + 0.99 * fc, False),
                     (COG_A - 1.01 * fc, True)):
        x = drive(open_sim(Rig(), coulomb_n=fc, cogging_n=COG_A, cogging_period_m=COG_P,
                           x0_m=x0), [u] * 50)
        assert np.any(x != x0) == moves


def test_cogging_needs_its_period():
    with pytest.raises(UserError, match="cogging_period_m"):
        open_sim(Rig(), cogging_n=0.01)
    with pytest.raises(UserError, match="cogging_period_m"):
        open_sim(Rig(), cogging_n=0.01, cogging_period_m=0.0)
