"""Before a run risks it: does this PC and bus hold the loop? (``labbench devices --timing``)

``measure`` opens nothing: it takes a device opened paced, as a run would open it, and
runs the loop's own calls (``read_raw`` then ``command(0.0)``, at the device's pace)
for the given time under the rig's real-time settings (``labbench.loop.realtime``), the
device enabled at zero force (or not, ``[preflight] enable = false``). What each sample
cost comes from the device itself when it offers ``labbench.device.TimingProbe``
(``timing_log``: per sample ``(due_s, start_s, answer_s, wire_s)``):

* pacing lateness, ``start - due``: how late the host sent its request (a CANopen SYNC)
  after its time; a request more than half a period late is a late SYNC. Of the cycles
  whose previous one was done before their time (the host slept and woke), it is the
  host's pacing floor under its present load;
* wait, ``answer - start``: what the device's stale limit measures as the loop sees it
  (SYNC sent -> every TPDO in the loop; a serial board: one frame's arrival -> the next
  one's);
* wire: the same round trip from the frames' own timestamps where the interface gives
  them (the kernel's for SocketCAN and udp_multicast; the sender's for python-can's
  virtual bus), i.e. without the host thread's own wake-up. Where there are such
  timestamps the stale limit is judged on them: an answer that arrived in time waits in
  the socket through a stall of the host thread and is read at once, no fault (60 s on
  CANopenNode: ten loop waits over 20 ms, the longest 115 ms, all host stalls; the run
  with that limit did not fault);
* response, ``command done - answer``: the host's compute and send;
* cycle, ``command done - due`` (or ``- answer`` without a schedule): what the period
  must hold.

During the measurement the device's stale limit is relaxed (the loop is to be
measured through a stall, not stopped by it) and judged afterwards against the limit
the run will use. Beside them: the loop's periods (``labbench.loop.timing.period_stats``),
the host's CPU per period (the loop thread's and the whole process's), the planned bus
load, and what the OS granted.

``judge`` turns that into one verdict (``labbench.readout.verdict``) with what to change:

* the stale limit holds when the longest wait is below two thirds of it (a run as long
  sees stalls as long, give or take: the third is the margin); it is too tight when
  ``SURE_FAULTS`` waits or more exceeded it (a run as long faults but for a chance of
  about e^-5); fewer, or none within the margin, is doubtful (a run may fault, with the
  chance said). Suggested: ``stale_periods = ceil(1.5 x longest wait / T)``;
* the sample time holds when the cycle's p99.9 is below 80 % of T and at most one
  period in a thousand overran (> 1.5 T); it fails when the cycle's p99 reaches T.
  The shortest that would hold: the larger of (p99.9 of request -> command out + p99.9
  of the pacing floor) / 0.8 and 1.5 x longest wait / the stale periods the device
  allows, rounded up to 0.1 ms;
* real-time scheduling refused while requests came late: grant it (``realtime.hint``);
* a simulated peer shares this machine, so a stall of the whole machine (a period beyond
  T) delays its answer when it falls while the loop waits for it: each such stall beyond
  the limit counts as that share of a fault (measured at 60 s: one 210 ms stall in the
  preflight's pacing, none in its waits, and the run faulted when one fell between a SYNC
  and the in-process drive's answer; six 30 ms stalls against 3 ms, the run did not).
  A hardware drive's answer waits in the socket through a host stall; but a stall trips
  the loop's own watchdog (hardware) and the drive's watch on the host (its RPDO timer,
  heartbeat consumer or life time: ``details["host_silence_limit"]``), judged as the
  stale limit is.

``write_rig`` puts the suggested limits into the rig file (tomlkit, comments kept,
backup: ``labbench.commissioning.write_tables``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from labbench.loop import timing as loop_timing
from labbench.device import TimingProbe
from labbench.errors import DeviceFault, UserError
from labbench.scales import is_number
from labbench.loop.realtime import RealtimeConfig, acquire, hint
from labbench.readout.verdict import DOUBTFUL, FAILED, OK, judge as judge_findings

STALE_MARGIN = 1.5  # suggested stale limit = this x the longest wait measured
CYCLE_SHARE = 0.8  # a cycle's p99.9 must leave this share of the period unused, or less
OVERRUN_RATE = 1e-3  # periods > 1.5 T allowed per period
RELAXED_STALE_S = 1.0  # during the measurement: a stall is measured, not a fault
# Waits beyond the stale limit that make a run as long fault for sure: k such events in the
# preflight, a run of its length sees none with a chance of about e^-k (0.7 % at 5).
SURE_FAULTS = 5
QUANTILES = (50, 99, 99.9)


@dataclass(frozen=True)
class PreflightConfig:
    """The rig's ``[preflight]`` table: ``enable`` (the drive enabled at zero force during
    the measurement; false: cyclic traffic with the power stage off) and ``seconds``."""

    enable: bool = True
    seconds: float = 10.0

    @classmethod
    def from_rig(cls, rig) -> "PreflightConfig":
        table = rig.section("preflight")
        where = f"{rig.source}: [preflight]"
        for name in table:
            if name not in ("enable", "seconds"):
                raise UserError(f"{where} {name}: unknown (known: enable, seconds)")
        enable = table.get("enable", True)
        if not isinstance(enable, bool):
            raise UserError(f"{where} enable must be true or false, got {enable!r}")
        return cls(enable, checked_seconds(table.get("seconds", 10.0), f"{where} seconds"))


def checked_seconds(value, what: str = "--timing") -> float:
    """``value`` (a number, or its text) as seconds in [0.1, 3600]; else one UserError."""
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise UserError(f"{what} must be a number of seconds, got {value!r}") from None
    ok = is_number(value)
    if not ok or not 0.1 <= value <= 3600:
        raise UserError(f"{what} must be a number of seconds in [0.1, 3600], got {value!r}")
    return float(value)


def _stats(x) -> dict:
    """p50, p99, p99.9, max and count of a series (s), NaNs left out; {} when empty."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return {}
    q = np.percentile(x, QUANTILES)
    return {"p50_s": float(q[0]), "p99_s": float(q[1]), "p999_s": float(q[2]),
            "max_s": float(x.max()), "n": int(x.size)}


def measure(device, rig, seconds: float, realtime: RealtimeConfig | None = None,
            enable: bool = True, warn=None) -> dict:
    """What the loop sees on ``device`` (opened paced) for ``seconds`` (module doc)."""
    desc = device.describe()
    if not desc.paced:
        raise UserError(f"{desc.kind} runs lock-step: the timing preflight needs it paced "
                        "(open it with realtime=True, or [sim] paced = true)")
    T = float(desc.sample_time_s)
    n = max(int(round(seconds / T)), 2)
    probe = device if isinstance(device, TimingProbe) else None
    log: list = []
    stale_s = None
    if probe is not None:
        stale_s = probe.stale_limit_s
        probe.stale_limit_s = max(stale_s, RELAXED_STALE_S)
        probe.timing_log = log
    periods, cpu, done = np.zeros(n), np.zeros(n), np.zeros(n)
    read, command = getattr(device, "read_raw", device.read), device.command
    perf, thread_time = time.perf_counter, time.thread_time
    rt = realtime or RealtimeConfig.from_rig(rig)
    timeout = max(RELAXED_STALE_S, 10 * T)
    k, fault = 0, None
    try:
        with acquire(rt, warn) as grant:
            if enable:
                device.enable(timeout=1.0)
            p0, w0 = time.process_time(), perf()
            prev = perf()
            try:
                for k in range(n):
                    c0 = thread_time()
                    read(timeout)
                    command(0.0)
                    now = perf()
                    cpu[k] = thread_time() - c0
                    periods[k], done[k], prev = now - prev, now, now
                k = n
            except DeviceFault as exc:  # even the relaxed limit: what it measured, and why
                fault = f"after {k * T:.3g} s: {exc}"
            process_s, wall_s = time.process_time() - p0, perf() - w0
            granted = dict(grant.record)
    finally:
        if probe is not None:
            probe.timing_log = None
            probe.stale_limit_s = stale_s
    if k < 2:
        raise DeviceFault(f"the timing preflight could not measure: the device faulted {fault}")
    n, periods, cpu, done = k, periods[:k], cpu[:k], done[:k]
    stalls = periods[1:] - T  # how much longer than a period each one was
    rows = np.array(log[-n:], float).reshape(-1, 4) if log else np.full((0, 4), np.nan)
    m = min(len(rows), n)  # the last m samples of the loop have their device's row
    due, start, answer, wire = (rows[len(rows) - m:, i] for i in range(4))
    end = done[n - m:]
    lateness = start - due
    # the host's pacing floor: the lateness of requests whose cycle found the previous one
    # done before its time (the host slept and woke); an overloaded loop's backlog is not it
    slept = np.r_[False, end[:-1] < due[1:]] if m else np.zeros(0, bool)
    silences = _silence_limits(desc, rig)
    # What decides a stale fault: the answer's arrival on the bus after the request (frame
    # timestamps), where the interface gives them: an answer that arrived in time waits in
    # the socket through a stall of the host thread and is read at once. Else the loop's.
    wired = bool(m) and np.mean(np.isfinite(wire)) > 0.9
    judged = wire if wired else answer - start
    out = {
        "device": desc.kind, "name": desc.name, "simulated": desc.simulated,
        "label": desc.label(), "T_s": T, "seconds": n * T, "cycles": n, "wall_s": wall_s,
        "enabled": enable, "realtime": granted,
        # who fixes the period ("" when the host does): a rig's sample_time_s is never
        # rewritten alone then (rig_changes)
        "period_fixed_by": desc.details.get("period_fixed_by", ""),
        "stale_limit_s": stale_s,
        "over_stale": int(np.sum(judged > stale_s)) if stale_s else 0,
        "stale_clock": "the bus (frame timestamps)" if wired else "the loop",
        "judged_wait": _stats(judged),
        # a simulated peer shares this machine: a stall of the host is one of its answer
        "shares_host": bool(desc.simulated),
        "stalls_over_stale": int(np.sum(stalls > stale_s)) if stale_s else 0,
        "answer_share": float(np.nanmean(answer - start) / T) if m else 0.0,
        "host_stall": _stats(stalls),
        "host_silence_limits": silences,
        "host_stalls_over": {name: int(np.sum(stalls > limit))
                             for name, limit in silences.items()},
        "pacing": _stats(lateness), "late_requests": int(np.sum(lateness > 0.5 * T)),
        "floor": _stats(lateness[slept]),
        # what a cycle needs of its period: from the request on (a board pacing itself
        # sends its frame on its own: the host's response alone)
        "needed": _stats(end - np.where(np.isfinite(due), start, answer)),
        "wait": _stats(answer - start), "wire": _stats(wire),
        "response": _stats(end - answer),
        "cycle": _stats(end - np.where(np.isfinite(due), due, answer)),
        "periods": loop_timing.period_stats(periods[1:], T, paced=True),
        "cpu": {"thread_per_period_s": float(np.mean(cpu)),
                "thread_p99_s": float(np.percentile(cpu, 99)),
                "process_per_period_s": process_s / n},
        "bus_load": desc.details.get("bus_load"),
        "stale_periods_max": getattr(probe, "stale_periods_max", None),
    }
    if probe is None:
        out["note"] = f"{desc.kind} reports no per-sample timing: loop periods only"
    if fault:
        out["fault"] = fault
    return out


def _silence_limits(desc, rig) -> dict:
    """What a host stall (no request, no command for that long) trips, by name: the loop's
    own watchdog on hardware (``labbench.loop.safety``; a simulator's records and goes on) and
    the device's watch on the host (``details["host_silence_limit"]``: name, seconds)."""
    from labbench.loop.safety import SafetyConfig

    out = {}
    if not desc.simulated:
        out["the loop's watchdog ([safety] watchdog_s)"] = SafetyConfig.from_rig(rig).watchdog_s
    watch = desc.details.get("host_silence_limit")
    if isinstance(watch, (list, tuple)) and len(watch) == 2:
        out[str(watch[0])] = float(watch[1])
    return out


def _nice_ceil(x: float, step: float = 1e-4) -> float:
    return math.ceil(x / step - 1e-9) * step


def judge(m: dict) -> dict:
    """One verdict on ``m`` (``measure``'s result) and the limits that would hold."""
    T, findings, suggest = m["T_s"], [], {}
    if m.get("fault"):  # beyond even the relaxed limit (a lost frame, a stall over a second)
        findings.append((FAILED, f"the device faulted during the measurement, {m['fault']}: "
                                 "a run faults so"))
    wait, cycle, stale = m.get("judged_wait") or m["wait"], m["cycle"], m["stale_limit_s"]
    top = m.get("stale_periods_max") or 100
    ms = _ms
    stall = m.get("host_stall") or {}
    if wait and stale:
        longest = wait["max_s"]
        # Faults to expect in a run as long: each wait beyond the limit is one; with a
        # simulated peer on this machine, a stall of the machine beyond it is one when it
        # falls while the loop waits for the answer (that share of the period).
        expected = float(m["over_stale"])
        if m.get("shares_host") and stall.get("max_s", 0.0) > longest:
            longest = stall["max_s"]
            expected += m.get("stalls_over_stale", 0) * min(1.0, m.get("answer_share", 1.0))
        periods = max(math.ceil(STALE_MARGIN * longest / T - 1e-9), 1)
        level = (OK if longest * STALE_MARGIN <= stale else
                 FAILED if expected >= SURE_FAULTS else DOUBTFUL)
        word = "holds" if level == OK else "too tight" if expected else "marginal"
        text = (f"stale limit {ms(stale)} ({stale / T:.3g} periods): {word}, longest wait "
                f"{ms(wait['max_s'])} (p99.9 {ms(wait['p999_s'])}"
                + (", on the bus" if m.get("stale_clock", "").startswith("the bus") else "")
                + ")")
        if longest > wait["max_s"]:
            text += (f", longest stall of this machine {ms(longest)} ("
                     f"{m.get('stalls_over_stale', 0)} beyond the limit: the simulated peer "
                     "shares it, and one that falls while the loop waits delays the answer)")
        if m["over_stale"]:
            text += f", {m['over_stale']} wait(s) longer"
        if expected:
            text += ": a run as long faults" + (
                "" if level == FAILED else
                f" with a chance of about {100 * (1 - math.exp(-expected)):.0f} %")
        if level != OK:
            if periods <= top:
                suggest["stale_periods"] = periods
                text += f"; stale_periods = {periods} would hold"
            else:
                text += f"; no stale_periods up to {top} holds at this sample time"
        findings.append((level, text))
    for name, limit in (m.get("host_silence_limits") or {}).items():
        if not stall:
            break
        over = int(m.get("host_stalls_over", {}).get(name, 0))
        level = (OK if stall["max_s"] * STALE_MARGIN <= limit else
                 FAILED if over >= SURE_FAULTS else DOUBTFUL)
        text = (f"{name} {ms(limit)}: {'holds' if level == OK else 'the host stalled'} "
                f"(longest stall {ms(stall['max_s'])}"
                + (f", {over} longer than it: a run as long stops there" if over else "")
                + ")")
        findings.append((level, text))
    if not cycle:  # no per-sample timing: the loop's periods alone
        over = m["periods"].get("overruns", 0)
        findings.append((OK if over <= OVERRUN_RATE * m["cycles"] else DOUBTFUL,
                         f"sample time {ms(T)}: {over} overrun(s) in {m['cycles']} periods "
                         "(no per-sample timing from this device)"))
    if cycle:
        over = m["periods"].get("overruns", 0) / max(m["cycles"] - 1, 1)
        level = (OK if cycle["p999_s"] <= CYCLE_SHARE * T and over <= OVERRUN_RATE
                 else FAILED if cycle["p99_s"] >= T else DOUBTFUL)
        text = (f"sample time {ms(T)}: {'holds' if level == OK else 'does not hold'}, cycle "
                f"p99 {ms(cycle['p99_s'])}, p99.9 {ms(cycle['p999_s'])}, "
                f"{m['periods'].get('overruns', 0)} overrun(s) in {m['cycles']} periods")
        findings.append((level, text))
    # the period a cycle needs when it keeps up: its own work from the request on, plus
    # the host's wake-up lateness when it slept (an overloaded loop's backlog excluded)
    needed = (m["needed"].get("p999_s", 0.0) + m["floor"].get("p999_s", 0.0)
              if m["needed"] else cycle.get("p999_s", 0.0) if cycle else 0.0)
    shortest = max(needed / CYCLE_SHARE, STALE_MARGIN * wait["max_s"] / top if wait else 0.0)
    if shortest:
        suggest["shortest_sample_time_s"] = _nice_ceil(shortest)
        if findings and findings[-1][0] != OK and cycle:
            if _nice_ceil(shortest) > T:
                suggest["sample_time_s"] = _nice_ceil(shortest)
            else:  # the cycle's own work fits: what overran was the host, stalled
                level, text = findings[-1]
                findings[-1] = (level, text + "; not the sample time's fault: the host "
                                "stalled (pacing p99.9 " + ms(m["pacing"].get("p999_s"))
                                + ", max " + ms(m["pacing"].get("max_s")) + "): a quieter "
                                "or real-time host, not a longer period")
    rt = m.get("realtime") or {}
    refused = rt.get("requested") and (rt.get("refused") or rt.get("policy") not in (
        "SCHED_FIFO", "HIGH_PRIORITY_CLASS"))
    if refused and (m["late_requests"] or m["periods"].get("overruns", 0)):
        findings.append((DOUBTFUL, f"real-time scheduling refused and {m['late_requests']} "
                                   f"request(s) went out late: {hint()}"))
        suggest["realtime"] = hint()
    verdict = judge_findings(findings)
    return {"verdict": verdict.as_dict(), "findings": [t for _, t in findings],
            "suggest": suggest, "line": verdict.line() if verdict.level != OK else
            "ok: " + "; ".join(t for _, t in findings)}


def _ms(s) -> str:
    from labbench.readout.numfmt import fmt

    return "-" if s is None else f"{fmt(s * 1e3, 3)} ms"


def rig_changes(m: dict, judged: dict, table: str) -> dict:
    """``{table: {fields}}`` of the rig file that ``--write-rig`` sets: the suggested
    ``stale_periods`` in the device's table, a longer ``[rig] sample_time_s`` when the
    rig's does not hold, unless the device fixes its period itself (a serial board's
    sketch: its period changes with the sketch, never in the rig file alone)."""
    s = judged["suggest"]
    out = {}
    if "stale_periods" in s and table:
        out[table] = {"stale_periods": s["stale_periods"]}
    if "sample_time_s" in s and not m.get("period_fixed_by"):
        out["rig"] = {"sample_time_s": s["sample_time_s"]}
    return out


def lines(m: dict, judged: dict) -> list[str]:
    """What a person reads (``labbench devices --timing``)."""
    ms = _ms

    def row(name: str, st: dict, extra: str = "") -> str:
        if not st:
            return f"{name}: not measured"
        return (f"{name}: p50 {ms(st['p50_s'])}, p99 {ms(st['p99_s'])}, p99.9 "
                f"{ms(st['p999_s'])}, max {ms(st['max_s'])}{extra}")

    out = [f"timing preflight: {m['label']}", f"  {m['seconds']:g} s at T = {ms(m['T_s'])}, "
           f"{'enabled at zero force' if m['enabled'] else 'not enabled'}; "
           + loop_timing.scheduling(m["realtime"])]
    if m["pacing"]:
        out.append("  " + row("host pacing (request after its time)", m["pacing"],
                              f"; {m['late_requests']} late (> T/2) of {m['cycles']}"))
        out.append("  " + row("host pacing floor (woken from sleep)", m["floor"]))
    limit = f"; stale limit {ms(m['stale_limit_s'])}" if m["stale_limit_s"] else ""
    if m["pacing"]:
        out.append("  " + row("wait for the answer (what the stale limit measures)", m["wait"],
                              limit))
    elif m["wait"]:  # a board pacing itself: its frames' interval and their jitter
        w = m["wait"]
        out.append("  " + row("frame interval (silence before each frame, what the stale "
                              "limit measures)", w, f"; jitter p99 - p50 "
                              f"{ms(w['p99_s'] - w['p50_s'])}{limit}"))
    if m["wire"]:
        out.append("  " + row("round trip on the bus (frame timestamps)", m["wire"]))
    out.append("  " + row("host response (answer in -> command out)", m["response"]))
    out.append("  " + row("cycle (due -> command out)", m["cycle"]))
    out.append("  " + loop_timing.summary(m["periods"]))
    if m.get("host_stall"):
        out.append("  " + row("host stalls (a period beyond T)", m["host_stall"]))
    c = m["cpu"]
    out.append(f"  host CPU per period: loop thread {ms(c['thread_per_period_s'])} (p99 "
               f"{ms(c['thread_p99_s'])}), whole process {ms(c['process_per_period_s'])}")
    if isinstance(m.get("bus_load"), (int, float)):
        out.append(f"  bus load at 1 Mbit/s: {100 * m['bus_load']:.1f} % planned")
    if m.get("note"):
        out.append(f"  note: {m['note']}")
    out.append(f"verdict: {judged['line']}")
    s = judged["suggest"]
    if "shortest_sample_time_s" in s:
        out.append(f"  shortest sample time that would hold: {ms(s['shortest_sample_time_s'])}")
    if "sample_time_s" in s and m.get("period_fixed_by"):
        out.append(f"  the period is fixed by {m['period_fixed_by']}: a sample time of "
                   f"{ms(s['sample_time_s'])} needs the sketch changed too (then [rig] "
                   "sample_time_s); --write-rig never writes it alone")
    return out
