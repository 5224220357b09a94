"""The runner: record stream, refusal before enabling, abort by stop event and by Ctrl-C,
device faults, safety trips; force zero and the device closed on every way out."""
from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from labbench import records
from labbench.device import DeviceDescription, DeviceFault
from labbench.errors import UserError
from labbench.rig import Rig
from labbench.runner import run, summarize
from labbench.registry import make_protocol
from labbench.sim_backend.sim_device import open_sim


class Spy:
    """A real simulated device that logs commands/enable/disable/close and can inject faults."""

    def __init__(self, kind="sim", fail_at=None, fail_with=None, **sim_options):
        self.dev = open_sim(Rig(), **sim_options)
        self.kind = kind
        self.commands: list[float] = []
        self.calls: list[str] = []
        self.reads = 0
        self.fail_at, self.fail_with = fail_at, fail_with

    def describe(self):
        d = self.dev.describe()
        return DeviceDescription(self.kind, d.name, d.sample_time_s, d.force_limit_n,
                                 d.position_limits_m, d.details)

    def enable(self, timeout=1.0):
        self.calls.append("enable")
        self.dev.enable(timeout)

    def disable(self, timeout=1.0):
        self.calls.append("disable")
        self.dev.disable(timeout)

    def emergency_stop(self):
        self.calls.append("estop")
        self.dev.emergency_stop()

    def command(self, force_n):
        self.commands.append(force_n)
        self.dev.command(force_n)

    def read(self, timeout):
        self.reads += 1
        if self.fail_at is not None and self.reads == self.fail_at:
            raise self.fail_with
        return self.dev.read(timeout)

    def close(self):
        self.calls.append("close")
        self.dev.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _kinds(recs):
    return [r["kind"] for r in recs]


def test_stream_order_and_start_record_contents():
    recs = []
    p = make_protocol("etfe", duration_s=5.0, seed=5)
    res = run(Spy(), p, [recs.append], rig=Rig())
    kinds = _kinds(recs)
    assert kinds[0] == "start" and kinds[1] == "descriptor" and kinds[-1] == "stop"
    assert kinds.count("start") == kinds.count("descriptor") == kinds.count("stop") == 1
    start = recs[0]
    for key in ("uid", "time", "software", "rig", "protocol", "seed", "precheck", "plant"):
        assert key in start
    assert start["seed"] == 5 and start["protocol"]["protocol"] == "etfe"
    assert start["protocol"]["K"] == 50.0 and start["rig"]["name"] == Rig().name
    assert start["software"].startswith("labbench ")
    assert recs[1]["channels"] == records.CHANNELS
    data = records.concat_pages(recs)
    assert len(data["t"]) == 5000 == res.n_samples
    # the excitation recorded is the white noise asked for (zero only while the gate was shut)
    ex = p.excitation()
    applied = data["excitation"] != 0
    np.testing.assert_allclose(data["excitation"][applied], ex[applied])
    assert applied.sum() > 4900
    assert recs[-1]["status"] == "success" and res.status == "success"
    assert recs[-1]["timing"]["p99_s"] > 0


def test_several_consumers_see_the_same_stream():
    a, b = [], []
    run(Spy(), make_protocol("chirp-id", duration_s=12.0, methods=("l2",)), [a.append, b.append],
        rig=Rig())
    assert a == b


def test_unstable_ve_is_refused_before_anything_is_enabled_or_recorded():
    spy, recs = Spy(), []
    p = make_protocol("etfe", ve="spring", K=400.0, B=0.0, w0_rad_s=None)
    with pytest.raises(UserError, match="refusing unstable spring"):
        run(spy, p, [recs.append], rig=Rig())
    assert recs == []
    assert "enable" not in spy.calls and spy.calls[-1] == "close"
    assert all(c == 0.0 for c in spy.commands)


def test_override_only_on_a_simulator():
    p = make_protocol("etfe", ve="spring", K=400.0, B=0.0, w0_rad_s=None, allow_unstable=True,
                      duration_s=2.0)
    spy = Spy(kind="canopen")
    with pytest.raises(UserError, match="simulator only"):
        run(spy, p, [], rig=Rig())
    assert spy.calls[-1] == "close"
    assert "enable" not in spy.calls
    # a real driver talking to a simulated peer: the caller who opened it says so
    res = run(Spy(kind="canopen"), p, [], rig=Rig(), simulated=True)
    assert res.n_samples > 0  # it ran (no refusal)
    with pytest.raises(UserError, match="simulator only"):
        run(Spy(kind="sim"), p, [], rig=Rig(), simulated=False)


def test_stop_event_aborts_with_zero_force_and_stop_record():
    spy, recs, stop = Spy(), [], threading.Event()

    def progress(fraction, message):
        if fraction > 0.3:
            stop.set()

    res = run(spy, make_protocol("etfe", duration_s=10.0, seed=1), [recs.append], stop=stop,
              progress=progress, rig=Rig())
    assert res.status == "aborted"
    assert recs[-1]["kind"] == "stop" and recs[-1]["status"] == "aborted"
    n = len(records.concat_pages(recs)["t"])
    assert 3000 <= n < 10000
    assert spy.commands[-1] == 0.0
    assert spy.calls[-1] == "close" and "disable" in spy.calls
    assert spy.dev.applied_n == 0.0 or not spy.dev.enabled
    assert res.results == {}


def test_keyboard_interrupt_aborts_with_zero_force_and_closes():
    spy, recs = Spy(fail_at=1500, fail_with=KeyboardInterrupt()), []
    res = run(spy, make_protocol("etfe", duration_s=5.0, seed=1), [recs.append], rig=Rig())
    assert res.status == "aborted" and "Ctrl-C" in res.reason
    assert recs[-1]["status"] == "aborted"
    assert spy.commands[-1] == 0.0 and not spy.dev.enabled
    assert spy.calls[-1] == "close"


def test_device_fault_fails_the_run_and_records_the_event():
    spy, recs = Spy(fail_at=800, fail_with=DeviceFault("amplifier over-temperature")), []
    res = run(spy, make_protocol("etfe", duration_s=5.0, seed=1), [recs.append], rig=Rig())
    assert res.status == "failed" and "over-temperature" in res.reason
    assert any(r["kind"] == "event" and "over-temperature" in r["reason"] for r in recs)
    assert recs[-1]["status"] == "failed"
    assert spy.commands[-1] == 0.0 and spy.calls[-1] == "close"


def test_safety_trip_in_a_protocol_that_does_not_expect_one_fails_it():
    # A soft spring and strong noise push the handle out of a narrow window.
    rig = Rig(position_limits_m=(-0.002, 0.002))
    recs = []
    p = make_protocol("etfe", ve="spring", K=5.0, B=0.0, w0_rad_s=None, std_n=1.0, duration_s=5.0,
                      seed=2)
    res = run(open_sim(rig), p, [recs.append], rig=rig)
    assert res.status == "failed" and "position" in res.reason
    assert any(r["kind"] == "event" and r["name"] == "position_limit" for r in recs)


def test_device_with_other_sample_time_is_refused():
    p = make_protocol("etfe", sample_time_s=0.002)
    with pytest.raises(UserError, match="samples every"):
        run(Spy(), p, [], rig=Rig())


def test_analysis_error_is_reported_not_raised(monkeypatch):
    from labbench.analysis import identify

    def refuses(*_a, **_kw):
        raise UserError("too little excitation to identify")

    monkeypatch.setattr(identify, "identify", refuses)
    p = make_protocol("chirp-id", duration_s=12.0, methods=("l2",))
    res = run(Spy(), p, [], rig=Rig())
    assert res.status == "failed" and res.cause == "analysis"
    assert "too little excitation" in res.results["error"]
    assert res.reason.startswith("recorded, but the analysis failed: too little excitation")


@pytest.mark.parametrize("name", ["etfe", "commission"])
def test_a_device_that_cannot_act_is_refused_before_anything_runs(name):
    class PositionOnly(Spy):
        def describe(self):
            return replace(super().describe(), cannot_act="it takes no force commands")

    spy, recs = PositionOnly(), []
    with pytest.raises(UserError, match=f"^{name} drives a force, but it takes no force commands$"):
        run(spy, make_protocol(name), [recs.append], rig=Rig())
    assert recs == [] and not any(spy.commands) and "enable" not in spy.calls


def test_bad_analysis_option_is_refused_before_the_run():
    with pytest.raises(UserError, match="did you mean 'mb'"):
        make_protocol("chirp-id", duration_s=12.0, model="mbx")
    with pytest.raises(UserError, match="did you mean 'lpm'"):
        make_protocol("etfe", duration_s=12.0, estimator="lmp")


def test_probe_segments_are_announced_and_homing_kept_apart():
    recs = []
    res = run(Spy(), make_protocol("stability", K=30.0, td_s=0.002), [recs.append], rig=Rig())
    segs = [r for r in recs if r["kind"] == "event" and r["name"] == "segment"]
    probes = [s for s in segs if s["role"] == "probe"]
    assert len(probes) == len(res.results["steps"]) >= 3
    assert any(s["role"] == "home" for s in segs)
    assert [s["K"] for s in res.results["steps"]] == [s["ve"]["K"] for s in probes]


def test_summarize_drops_long_arrays_only():
    s = summarize({"a": np.arange(100), "b": 1.5, "c": {"d": [1, 2], "e": np.zeros(70)}})
    assert s == {"b": 1.5, "c": {"d": [1, 2]}}


def test_ctrl_c_before_the_start_record_emits_nothing_and_closes():
    spy, recs = Spy(), []
    p = make_protocol("etfe", duration_s=2.0)

    def interrupted(*_):
        raise KeyboardInterrupt

    p.check_plan = interrupted  # Ctrl-C while the precheck runs
    res = run(spy, p, [recs.append], rig=Rig())
    assert res.status == "aborted" and recs == []
    assert "enable" not in spy.calls and spy.calls[-1] == "close"


def test_ctrl_c_during_analysis_still_ends_the_stream():
    spy, recs = Spy(), []
    p = make_protocol("etfe", duration_s=2.0, seed=1)

    def interrupted(*_):
        raise KeyboardInterrupt

    p.analyze = interrupted
    res = run(spy, p, [recs.append], rig=Rig())
    assert res.status == "aborted" and recs[-1]["kind"] == "stop"
    assert recs[-1]["status"] == "aborted" and spy.calls[-1] == "close"


def test_a_crashing_analysis_keeps_the_recording():
    spy, recs = Spy(), []
    p = make_protocol("etfe", duration_s=2.0, seed=1)

    def broken(*_):
        raise IndexError("index -1 is out of bounds")

    p.analyze = broken
    res = run(spy, p, [recs.append], rig=Rig())
    assert res.status == "failed" and res.cause == "analysis" and "IndexError" in res.reason
    assert "IndexError" in res.results["error"]
    stop = recs[-1]
    assert stop["kind"] == "stop" and "IndexError" in stop["results"]["error"]
    assert stop["status"] == "failed" and stop["cause"] == "analysis"
    assert len(records.concat_pages(recs)["t"]) == 2000
