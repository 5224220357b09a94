"""Loop timing a user sees: period statistics, segments merged, a stall found where it happened."""
from __future__ import annotations

import time

import numpy as np
import pytest

from labbench import records
from labbench.loop import timing
from labbench.loop.chain import HapticLoop, SafetyConfig, run_loop
from labbench.rig import Rig
from labbench.runner import run
from labbench.registry import make_protocol
from labbench.sim_backend.sim_device import open_sim
from labbench.model.ve import VirtualEnvironment

T = 1e-3


def test_period_stats_counts_bins_overruns_and_the_worst():
    p = np.full(1000, T)
    p[[10, 20]] = 1.6 * T  # overruns
    p[30] = 1.4 * T  # late, not an overrun
    p[500] = 25 * T  # the worst stall: open-ended last bin
    p[600] = 0.3 * T
    s = timing.period_stats(p, T, paced=True, worst_sample=501, worst_t_s=0.501)
    assert s["overruns"] == 3 and s["periods"] == 1000
    assert s["max_s"] == pytest.approx(25 * T) and s["worst"]["sample"] == 501
    counts = dict(zip(timing.EDGES_T, s["histogram"]["counts"]))
    assert counts[0.0] == 1 and counts[0.9] == 995 and counts[1.1] == 1 and counts[1.5] == 2
    assert counts[20.0] == 1 and sum(counts.values()) == 1000
    assert timing.period_stats(p, T, paced=False)["overruns"] == 0  # unpaced: compute times


def test_merge_adds_counts_and_places_the_worst_in_the_run():
    a = timing.period_stats(np.full(100, T), T, True, worst_sample=5, worst_t_s=0.005)
    b = timing.period_stats(np.r_[np.full(99, T), 3 * T], T, True, worst_sample=99, worst_t_s=0.2)
    m = timing.merge([a, b], [0, 100])
    assert m["segments"] == 2 and m["periods"] == 200 and m["overruns"] == 1
    assert m["worst"]["sample"] == 199 and m["worst"]["t_s"] == 0.2
    assert sum(m["histogram"]["counts"]) == 200 and m["max_s"] == pytest.approx(3 * T)
    rows = dict(timing.report_rows(m))
    assert rows["overruns (> 1.5 T)"] == 1 and rows["periods in [3 T, 5 T)"] == 1
    assert "1 overruns" in rows["summary"] and "at t = 0.200 s" in rows["summary"]


class _Stall:
    """A consumer that stalls the loop once, at the flush of page ``at`` (page_size 100)."""

    def __init__(self, at: int, seconds: float):
        self.at, self.seconds, self.pages = at, seconds, 0

    def __call__(self, rec):
        if rec["kind"] == records.PAGE:
            if rec["index"] == self.at:
                time.sleep(self.seconds)
            self.pages += 1


def test_a_stall_is_found_where_it_happened():
    """A 150 ms stall after page 3 (samples 0..399): the sample late is 400, t = 0.4 s."""
    rig = Rig(sections={"safety": {"watchdog_s": 1.0}})
    ve = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0, T=T)
    dev = open_sim(rig, realtime=True)
    snaps = []
    out = run_loop(dev, HapticLoop(ve, SafetyConfig.from_rig(rig)), np.zeros(600),
                   _Stall(3, 0.15), live=snaps.append)
    t = out.timing
    assert out.status == "completed" and t["paced"]
    assert t["worst"]["sample"] == 400 and t["worst"]["t_s"] == pytest.approx(0.4)
    assert t["max_s"] >= 0.15 and t["overruns"] >= 1 and t["histogram"]["counts"][-1] >= 1
    assert [s["n"] for s in snaps] == [100, 200, 300, 400, 500, 600]
    assert snaps[-1]["max_s"] == t["max_s"] and snaps[-1]["overruns"] == t["overruns"]
    assert snaps[3]["max_s"] < 0.15 <= snaps[4]["max_s"]  # seen live, one page later


def test_stream_records_timing_and_what_the_scheduler_granted():
    recs, live = [], []
    res = run(open_sim(Rig(), realtime=True), make_protocol("etfe", duration_s=1.0, seed=1),
              [recs.append], rig=Rig(), live_timing=live.append)
    start, stop = recs[0], recs[-1]
    rt = start["realtime"]
    assert rt["requested"] and set(rt) >= {"policy", "priority", "affinity", "memory_locked", "gc",
                                           "cpu_latency_us"}
    assert stop["timing"]["realtime"] == rt and res.timing["realtime"] == rt
    if rt["cpu_latency_us"] is not None:  # granted: the one line of the report and CLI says so
        assert "CPU wake-up latency <= 0 us" in timing.summary(stop["timing"])
    assert rt["gc"] == "frozen, disabled"
    if rt["policy"] == "SCHED_FIFO":  # granted (root, CAP_SYS_NICE or an rtprio limit)
        assert not any(r.startswith("SCHED_FIFO") for r in rt["refused"])
    t = stop["timing"]
    assert sum(t["histogram"]["counts"]) == t["periods"] == res.n_samples - 1
    assert live and live[-1]["n"] == res.n_samples and live[-1]["max_s"] == t["max_s"]


def test_an_unpaced_run_asks_for_nothing():
    recs = []
    run(open_sim(Rig()), make_protocol("etfe", duration_s=1.0, seed=1), [recs.append], rig=Rig())
    rt = recs[0]["realtime"]
    assert rt["requested"] is False and rt["policy"] != "SCHED_FIFO"
    assert recs[-1]["timing"]["overruns"] == 0
