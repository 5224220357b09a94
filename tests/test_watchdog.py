"""The watchdog policy (labbench.loop.safety.WatchdogPolicy): a host stall on a simulator is
recorded and the run goes on; on hardware the same stall trips."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from gui_faulty_device import StallingDevice  # noqa: E402

from labbench.registry import make_protocol  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.runner import run  # noqa: E402
from labbench.loop.safety import OVERRUN, SafetyConfig, WatchdogPolicy  # noqa: E402

STALL_S = 0.2  # four times the default watchdog (50 ms)


def _run(simulated: bool):
    # a commissioned rig: the hardware arm must meet the watchdog, not the commissioning gate
    rig = Rig(direction_checked="2026-12-02, a commission session")
    records = []
    device = StallingDevice(rig, at=400, stall_s=STALL_S)
    result = run(device, make_protocol("etfe", duration_s=1.0, seed=1), [records.append], rig=rig,
                 simulated=simulated)
    assert device.stalls == 1
    return result, records


def test_a_stall_on_a_simulator_is_recorded_and_the_run_goes_on():
    result, records = _run(simulated=True)
    assert result.status == "success", result.reason
    assert result.n_samples == 1000
    start = records[0]
    assert start["watchdog"] == {"applies": "simulator", "period_limit_s": None,
                                 "sample_timeout_s": 5.0, "late_period": "recorded, run goes on"}
    # the timing and the flags keep the stall
    assert result.timing["max_s"] >= STALL_S and result.timing["overruns"] >= 1
    flags = np.concatenate([r["data"]["flags"] for r in records if r["kind"] == "page"])
    assert np.count_nonzero(flags & OVERRUN) >= 1
    stalls = [r for r in records if r["kind"] == "event" and r["name"] == "stall"]
    assert len(stalls) == 1 and "simulator: recorded, run goes on" in stalls[0]["reason"]


def test_the_same_stall_on_hardware_trips_the_watchdog():
    result, records = _run(simulated=False)
    assert result.status == "failed" and "watchdog: loop period" in result.reason
    assert result.n_samples < 1000
    assert records[0]["watchdog"]["applies"] == "hardware"
    assert records[0]["watchdog"]["period_limit_s"] == 0.05


def test_policy_from_the_safety_settings():
    safety = SafetyConfig(watchdog_s=0.02)
    hw = WatchdogPolicy.for_device(safety, simulated=False)
    assert (hw.period_limit_s, hw.sample_timeout_s) == (0.02, 0.02)
    sim = WatchdogPolicy.for_device(SafetyConfig(watchdog_s=8.0), simulated=True)
    assert sim.period_limit_s == float("inf") and sim.sample_timeout_s == 8.0
    assert pytest.approx(WatchdogPolicy.for_device(safety, True).sample_timeout_s) == 5.0
