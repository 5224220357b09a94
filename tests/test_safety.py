"""Safety envelope: every piece exercised by injecting its fault into a run."""
import time

import numpy as np
import pytest

from labbench import records
from labbench.device import DeviceDescription, DeviceFault, Sample
from labbench.errors import UserError
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.rig import Rig, rig_from_dict
from labbench.loop.safety import CLAMP, DEVICE, FADE, GATED, OVERRUN, RATE, SEQ_GAP, TRIPPED, flag_names
from labbench.model.linear import k_max, stability
from labbench.model.ve import Plant, VirtualEnvironment
from labbench.sim_backend.sim_device import open_sim

PLANT = Plant(0.094, 0.10)
NONE = VirtualEnvironment("none")


def safety(**kw):
    base = {"force_limit_n": 5.0, "force_rate_limit_n_per_s": 1e9, "velocity_limit_m_s": 100.0,
            "position_limits_m": (-10.0, 10.0), "energy_limit_j": 1e3, "watchdog_s": 0.05,
            "nominal_damping_ns_m": PLANT.b}
    return SafetyConfig(**{**base, **kw})


def run(ve, exc, cfg, device=None):
    recs = []
    device = device or open_sim(Rig())
    out = run_loop(device, HapticLoop(ve, cfg), np.asarray(exc, float), recs.append)
    events = [r for r in recs if r["kind"] == records.EVENT]
    return out, records.concat_pages(recs), events, device


class Faulty:
    """A simulated device with one fault injected at sample ``at`` (a Device by delegation)."""

    def __init__(self, at, fault, paced=False, dev=None):
        self.dev = dev or open_sim(Rig())
        self.at, self.fault, self.paced = at, fault, paced
        self.commands, self.calls = [], []
        self.k = 0

    def describe(self):
        d = self.dev.describe()
        return DeviceDescription(d.kind, d.name, d.sample_time_s, d.force_limit_n,
                                 d.position_limits_m, {**d.details, "paced": self.paced})

    def read_raw(self, timeout):
        seq, t, x, flags = self.dev.read_raw(timeout)
        k, self.k = self.k, self.k + 1
        if k == self.at:
            if self.fault == "timeout":
                raise TimeoutError("injected: samples stopped")
            if self.fault == "fault":
                raise DeviceFault("injected: drive fault")
            if self.fault == "late":
                time.sleep(0.08)
        if self.fault == "gap" and k >= self.at:
            seq += 3
        if self.fault == "flags" and k == self.at:
            flags = 4
        return seq, t, x, flags

    def command(self, u):
        self.commands.append(u)
        self.dev.command(u)

    def __getattr__(self, name):  # enable, disable, emergency_stop, close
        target = getattr(self.dev, name)  # what the device lacks, the wrapper lacks too

        def call(*a, **kw):
            self.calls.append(name)
            return target(*a, **kw)
        return call


def test_force_clamp_holds_the_limit_and_reports_it():
    out, d, events, _ = run(NONE, [0.0] + [8.0] * 19 + [-8.0] * 5, safety())
    assert out.status == "completed"
    assert np.max(np.abs(d["command"])) == 5.0
    assert np.all(d["flags"][1:] & CLAMP)
    assert out.stats["clamp"] == 24
    assert [e["name"] for e in events] == ["enabled", "clamp"]  # at most one event a second
    np.testing.assert_array_equal(d["excitation"][1:], [8.0] * 19 + [-8.0] * 5)


def test_force_rate_limit_ramps_a_step():
    _, d, events, _ = run(NONE, [0.0] + [3.0] * 10, safety(force_rate_limit_n_per_s=500.0))
    np.testing.assert_allclose(d["command"], [0, .5, 1, 1.5, 2, 2.5, 3, 3, 3, 3, 3], atol=1e-12)
    assert list(d["flags"][1:6] & RATE) == [RATE] * 5 and not np.any(d["flags"][6:])
    assert "rate" in [e["name"] for e in events]


def test_velocity_limit_trips_and_zeroes_force_at_once():
    out, d, events, dev = run(NONE, [0.0] + [4.0] * 200, safety(velocity_limit_m_s=0.5))
    assert out.status == "tripped" and "velocity" in out.reason
    k = int(np.argmax(np.abs(d["velocity"]) > 0.5))
    assert out.n_done == k + 1 == len(d["t"])  # the run ends at the tripping sample
    assert d["command"][k] == 0.0 and d["flags"][k] & TRIPPED
    assert np.all(np.abs(d["velocity"][:k]) <= 0.5)
    assert events[-1]["name"] == "velocity_limit"
    assert dev.enabled is False and dev._u == 0.0


def test_position_window_trips_when_the_handle_leaves_it():
    out, d, events, _ = run(NONE, [0.0] + [1.0] * 500, safety(position_limits_m=(-0.01, 0.005)))
    assert out.status == "tripped" and events[-1]["name"] == "position_limit"
    assert d["position"][-1] > 0.005 and np.all(d["position"][:-1] <= 0.005)
    assert d["command"][-1] == 0.0


@pytest.mark.parametrize("K", [150.0, 300.0])
def test_energy_observer_trips_exactly_the_unstable_spring(K):
    # b = 0.1, T = 1 ms: the exact sampled boundary is K_max = 200 N/m.
    ve = VirtualEnvironment("spring", K=K)
    unstable = not stability(PLANT, ve).stable
    assert unstable == (K > k_max(PLANT, ve))
    exc = np.random.default_rng(0).normal(0, 0.05, 20000)
    exc[0] = 0.0
    cfg = safety(energy_limit_j=1e-3, energy_fade_s=0.02)
    out, d, events, _ = run(ve, exc, cfg, device=open_sim(Rig(), m=PLANT.m, b=PLANT.b))
    if not unstable:
        assert out.status == "completed" and out.stats["energy_max_j"] < 1e-3 / 10
        return
    assert out.status == "tripped" and events[-1]["name"] == "energy"
    fading = np.flatnonzero(d["flags"] & FADE)
    assert len(fading) == 20  # energy_fade_s / T samples, force scaled down linearly
    assert [e["name"] for e in events][-2:] == ["energy", "energy"]  # onset, then trip
    assert d["command"][-1] == 0.0 and np.abs(d["position"]).max() < 0.1  # caught early


def test_energy_observer_stays_quiet_on_the_papers_spring_damper():
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)
    exc = np.random.default_rng(1).normal(0, 1.0, 30000)
    exc[0] = 0.0
    out, _, _, _ = run(ve, exc, SafetyConfig.from_rig(Rig()))
    assert out.status == "completed"
    assert out.stats["energy_max_j"] < SafetyConfig().energy_limit_j / 100


def test_watchdog_zeroes_force_when_samples_stop():
    dev = Faulty(at=30, fault="timeout")
    out, _, events, _ = run(NONE, [0.0] + [0.5] * 99, safety(), device=dev)
    assert out.status == "tripped" and "no sample" in out.reason and out.n_done == 30
    assert events[-1]["name"] == "watchdog"
    assert dev.commands[-1] == 0.0 and dev.calls[-1] == "disable"
    assert dev.dev._u == 0.0


def test_watchdog_trips_on_a_paced_loop_overrun():
    dev = Faulty(at=20, fault="late", paced=True)
    out, d, _, _ = run(NONE, [0.0] + [0.5] * 99, safety(), device=dev)
    assert out.status == "tripped" and "loop period" in out.reason
    assert d["flags"][-1] & OVERRUN and d["flags"][-1] & TRIPPED and d["command"][-1] == 0.0
    assert out.timing["overruns"] >= 1 and out.timing["max_s"] >= 0.08


def test_device_fault_ends_the_run_with_force_off():
    dev = Faulty(at=10, fault="fault")
    out, _, events, _ = run(NONE, [0.0] + [0.5] * 50, safety(), device=dev)
    assert out.status == "fault" and "drive fault" in out.reason
    assert events[-1]["name"] == "device_fault"
    assert "emergency_stop" in dev.calls and dev.commands[-1] == 0.0


def test_sequence_gaps_and_device_flags_are_flagged():
    out, d, events, _ = run(NONE, np.zeros(30), safety(), device=Faulty(at=10, fault="gap"))
    assert list(np.flatnonzero(d["flags"] & SEQ_GAP)) == [10] and out.stats["seq_gap"] == 1
    assert "seq_gap" in [e["name"] for e in events]
    _, d, _, _ = run(NONE, np.zeros(30), safety(), device=Faulty(at=5, fault="flags"))
    assert list(np.flatnonzero(d["flags"] & DEVICE)) == [5]


class Scripted:
    """A handle moved by hand along a fixed path (the Device protocol, no read_raw)."""

    def __init__(self, path):
        self.path, self.k = list(path), 0
        self.enabled_at, self.commands = None, []

    def describe(self):
        return DeviceDescription("scripted", "hand", 0.001, 5.0, (-1.0, 1.0), {"paced": False})

    def read(self, timeout):
        k, self.k = self.k, self.k + 1
        return Sample(k, k * 0.001, self.path[k])

    def enable(self, timeout=1.0):
        if self.enabled_at is None:
            self.enabled_at = self.k - 1

    def command(self, u):
        self.commands.append(u)

    def disable(self, timeout=1.0):
        pass

    def emergency_stop(self):
        pass


def test_enable_gate_waits_until_the_handle_leaves_the_wall():
    # Started 5 cm inside a 50 N/m wall (2.5 N): enabling there would kick the handle.
    path = np.linspace(0.05, -0.01, 121)
    dev = Scripted(path)
    cfg = safety(enable_force_threshold_n=0.2)
    _, d, events, _ = run(VirtualEnvironment("spring", K=50.0), np.full(120, 0.05), cfg,
                          device=dev)
    k = dev.enabled_at
    assert k == int(np.argmax(np.abs(0.05 - 50.0 * path) <= 0.2))  # first sample |u| <= 0.2 N
    assert np.all(d["command"][:k] == 0.0) and np.all(d["flags"][:k] & GATED)
    assert np.all(d["excitation"][:k] == 0.0) and d["excitation"][k] == 0.05
    assert abs(d["command"][k]) <= 0.2 and not d["flags"][k] & GATED
    assert events[0]["name"] == "enabled"


@pytest.mark.parametrize("n", [0, 2, 5])
@pytest.mark.parametrize("v0", [0.0, -0.2], ids=["at-rest", "leaving"])
def test_enable_inside_a_spring_wall_never_jumps_for_any_delay(n, v0):
    # Fault: the simulated handle starts 2 cm inside a 50 N/m spring (1 N), at rest or
    # drifting out through the centre. Enabling while f_ve[k-n..k] still holds large
    # forces would put K x on the handle n samples after the enable (the td > 0 bug).
    K, x0, gate, rate = 50.0, 0.02, 0.2, 500.0  # rate: 0.5 N a sample < K x0
    ve = VirtualEnvironment("spring", K=K, td=n * 0.001)
    cfg = safety(enable_force_threshold_n=gate, force_rate_limit_n_per_s=rate)
    out, d, events, dev = run(ve, np.zeros(400), cfg, device=open_sim(Rig(), x0_m=x0, v0_m_s=v0))
    assert out.status == "completed"
    u, f, x, flags = d["command"], d["ve_force"], d["position"], d["flags"]
    np.testing.assert_allclose(f, K * x, rtol=1e-12)
    gated = (flags & GATED) != 0
    if v0 == 0.0:  # nothing moves the handle out: the device is never enabled
        assert np.all(gated) and np.all(u == 0.0) and dev.applied_n == 0.0
        assert "enabled" not in [e["name"] for e in events]
        return
    k0 = int(np.argmin(gated))
    assert np.all(gated[:k0]) and not np.any(gated[k0:]) and np.all(u[:k0] == 0.0)
    # it opened at the first sample where the command now and every one in the
    # line after it (up to the undelayed f_ve[k0]) is small
    small = np.abs(f) <= gate
    held = np.array([k >= n and np.all(small[k - n:k + 1]) for k in range(len(f))])
    assert k0 == int(np.argmax(held)) and abs(x[0]) * K > gate
    # no jump: |u| <= gate at enable, then the rate limit is never needed
    du = np.abs(np.diff(u, prepend=0.0))
    assert np.max(du) <= gate + rate * ve.T and not np.any(flags & RATE)
    assert abs(u[k0]) <= gate
    np.testing.assert_allclose(u[k0:], -f[k0 - n:len(f) - n], rtol=1e-12, atol=1e-15)


def test_safety_settings_come_from_the_rig_with_one_clear_error_each():
    rig = rig_from_dict({"rig": {"force_limit_n": 3.0, "nominal_damping_ns_m": 0.2},
                         "safety": {"energy_limit_j": 0.01, "watchdog_s": 0.02}})
    cfg = SafetyConfig.from_rig(rig)
    assert (cfg.force_limit_n, cfg.energy_limit_j, cfg.watchdog_s) == (3.0, 0.01, 0.02)
    assert cfg.nominal_damping_ns_m == 0.2 and cfg.position_limits_m == (-0.1, 0.1)
    for table, field in (({"energy_limit_j": -1}, "energy_limit_j"),
                         ({"watchdog_s": "soon"}, "watchdog_s"),
                         ({"watchdogs": 1.0}, "watchdogs"),
                         ({"enable_force_threshold_n": True}, "enable_force_threshold_n")):
        with pytest.raises(UserError) as err:
            SafetyConfig.from_rig(rig_from_dict({"safety": table}, source="r.toml"))
        assert "r.toml" in str(err.value) and field in str(err.value)
    with pytest.raises(UserError, match="position_limits_m"):
        SafetyConfig(position_limits_m=(0.1, -0.1))


def test_flag_names():
    assert flag_names(CLAMP | TRIPPED) == ["clamp", "tripped"]
    assert flag_names(0) == []


def test_rig_nominal_model_fields_are_validated():
    rig = rig_from_dict({"rig": {"nominal_mass_kg": 0.2, "nominal_damping_ns_m": 0}})
    assert rig.nominal_plant == Plant(0.2, 0.0) and Rig().nominal_plant == PLANT
    assert rig.as_dict()["nominal_mass_kg"] == 0.2
    for field, value in (("nominal_mass_kg", 0), ("nominal_damping_ns_m", -0.1),
                         ("nominal_damping_ns_m", "x")):
        with pytest.raises(UserError, match=field):
            rig_from_dict({"rig": {field: value}})


@pytest.mark.parametrize("td", [0.0, 0.002, 0.005, 0.02])
@pytest.mark.parametrize("kind,K,B", [("spring-damper", 50.0, 1.0), ("spring", 50.0, 0.0),
                                      ("damper", 0.0, 1.0)])
def test_energy_observer_trips_iff_the_exact_sampled_loop_is_unstable(kind, K, B, td):
    # The rig's default envelope, white noise of 1 N std for 20 s on the nominal device.
    ve = VirtualEnvironment(kind, K=K, B=B, w0=125.0, td=td)
    exc = np.random.default_rng(0).normal(0, 1.0, 20000)
    exc[0] = 0.0
    out, _, events, _ = run(ve, exc, SafetyConfig.from_rig(Rig()))
    energy_trip = out.status == "tripped" and events[-1]["name"] == "energy"
    assert energy_trip == (not stability(PLANT, ve).stable)
    if not energy_trip:  # a free damper may drift out of the window; nothing else may stop it
        assert out.status == "completed" or events[-1]["name"] == "position_limit"
