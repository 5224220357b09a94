"""Run one protocol on one device: precheck, records, the loop, analysis, safe shutdown.

The whole run is one record stream (labbench.records): ``start`` -> ``descriptor``
-> pages and events from ``labbench.loop.chain.run_loop`` (one call per protocol
segment, each announced by a ``segment`` event) -> ``stop``. Every consumer
sees every record in order. Whatever happens (a refused VE, Ctrl-C, the stop
event, a device fault, a bug) the force is set to zero, the device disabled
and closed, and - once a start record went out - a stop record follows.

On a paced device the segments run under ``labbench.loop.realtime.acquire``
(SCHED_FIFO, CPU affinity, locked memory, GC frozen; the analysis after them
does not); the start record's ``realtime`` and the stop record's
``timing.realtime`` say what the OS granted, ``timing`` (``labbench.loop.timing``)
how well the loop kept time. A device that reports its link counters
(``StatusReporting``: stray frames, EMCYs, late SYNCs, CRC errors, ...) has them
as they stand at each segment's start (its ``segment`` event), at its end (its
row in the segment table) and after the run (the stop record), as
``device_counters``. Each row of the segment table also keeps the peak energy the loop's
passivity observer saw in it (``energy_max_j``, ``labbench.loop.chain``).
"""
from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from labbench import commissioning
from labbench.model import device_delay
from labbench.model import device_friction
from labbench import records
from labbench.loop import timing as loop_timing
from labbench.jsonutil import json_safe
from labbench.device import StatusReporting
from labbench.errors import DeviceError, RecordingError, UserError
from labbench.loop.realtime import RealtimeConfig, acquire
from labbench.rig import Rig
from labbench.protocol import ProtocolBase, SegmentOutcome, precheck

# run_loop outcome -> stop-record status (a trip a protocol expects is not a failure).
_FAILED = ("tripped", "fault")
_CAUSE = {"tripped": "safety", "fault": "device"}  # the failed stop record's ``cause``


@dataclass
class RunResult:
    """What ``run`` returns: stop status and reason, the protocol's results, loop timing."""

    status: str  # "success" | "aborted" | "failed"
    reason: str
    results: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)
    uid: str | None = None
    n_samples: int = 0
    cause: str | None = None  # of a failed run: "device", "safety", "recording", "analysis", "error"


def run_recorded(device, protocol: ProtocolBase, session_dir, consumers=(),
                 start_extra: dict | None = None,
                 on_session: Callable[[str], None] | None = None, **options):
    """The one way a run is driven (``labbench run`` and the GUI's acquisition process):
    ``run(device, protocol, ...)`` recording a session in ``session_dir`` (None: none)
    ahead of ``consumers``. ``start_extra`` fields are added to the start record as
    written; ``on_session(path)`` hears where the session went, even if the run raised.
    ``options`` are ``run``'s. Returns (RunResult, session path or None when the run
    was refused before its start record)."""
    from labbench.sessions.session_format import SessionWriter

    sinks = list(consumers)
    try:  # the folder is checked for writing here, before the device is enabled
        writer = SessionWriter(session_dir) if session_dir is not None else None
    except BaseException:
        _stop_device(device, close=options.get("close", True))
        raise
    if writer is not None:
        def record(rec, _write=writer):
            _write({**rec, **start_extra} if start_extra and rec["kind"] == records.START else rec)

        sinks.insert(0, record)
    try:
        result = run(device, protocol, sinks, **options)
    finally:
        if writer is not None:
            writer.close()
            if writer.path is not None and on_session is not None:
                on_session(str(writer.path))
    if writer is not None and writer.error is not None and result.cause != "recording":
        # refused at the last flush: the run is done but its session may not be whole
        result = replace(result, status="failed", reason=writer.failure(), cause="recording")
    return result, writer.path if writer else None


def run(device, protocol: ProtocolBase, consumers: Iterable[records.Consumer],
        stop: threading.Event | None = None,
        progress: Callable[[float, str], None] | None = None, rig: Rig | None = None,
        close: bool = True, simulated: bool | None = None,
        realtime: RealtimeConfig | None = None,
        live_timing: Callable[[dict], None] | None = None,
        warn: Callable[[str], None] | None = None,
        skip_commissioning: bool = False) -> RunResult:
    """Run ``protocol`` on an open ``device`` and feed the record stream to ``consumers``.

    ``stop`` (a ``threading.Event`` or ``labbench.loop.interrupts.StopRequest``, set from
    another thread, e.g. a GUI's stop button, or by a signal handler) or Ctrl-C ends
    the run with status "aborted" and zero force; the stop record's reason is the
    request's ``reason`` when it has one. ``progress(fraction, message)``
    is called from this thread. ``rig`` gives calibration, limits and the nominal
    plant (default: the simulated Phantom-like rig). The device is disabled and,
    with ``close`` (default), closed on the way out. Raises UserError (before
    anything is enabled or recorded) when the protocol's VE is unstable or its
    plan does not fit the rig. ``simulated`` says whether the device is a
    simulator (the only place ``allow_unstable`` is accepted, and its watchdog records a
    host stall instead of tripping: ``labbench.loop.safety.WatchdogPolicy``); None: its
    description says so (``DeviceDescription.simulated``, or a kind starting with "sim").
    ``realtime``: what the loop's thread asks the OS for on a paced device
    (default ``RealtimeConfig()``: on); ``warn(line)`` gets the one line saying
    how to grant what was refused (default: a logging warning).
    ``live_timing(snapshot)``: the run's timing so far after each page (overruns,
    max_s, worst_t_s, n, wall_s, T_s, paced), e.g. for a status bar
    (``labbench.loop.timing.status_figures``). ``skip_commissioning``: render a spring
    or damper on real hardware before the rig passed its direction check
    (``labbench.commissioning.gate``).
    """
    from labbench.loop.chain import SafetyConfig
    from labbench.loop.safety import WatchdogPolicy

    rig = rig or Rig()
    stop = stop or threading.Event()
    consumers = list(consumers)
    run_state = _Run(consumers)
    run_state.counters = lambda: device_counters(device)
    try:
        desc = device.describe()
        T = float(desc.sample_time_s)
        if abs(T - protocol.ve.T) > 1e-9 * T:
            raise UserError(f"the device samples every {T:g} s but the protocol assumes "
                            f"{protocol.ve.T:g} s (set sample_time_s)")
        if simulated is None:
            simulated = bool(desc.simulated) or str(desc.kind).startswith("sim")
        if protocol.allow_unstable and not simulated:
            raise UserError(f"allow_unstable is for the simulator only, not a {desc.kind} device")
        plant, delay, check = checks(protocol, rig, desc, simulated, skip_commissioning)
        friction = protocol.device_friction  # resolved by checks
        safety = SafetyConfig.from_rig(rig)
        rt = realtime or RealtimeConfig()
        if not desc.details.get("paced", True):  # as fast as it can: nothing to keep time with
            rt = replace(rt, enabled=False)
        watchdog = WatchdogPolicy.for_device(safety, simulated)
        meta = _segments(device, protocol, rig, plant, check, delay, friction, safety, watchdog,
                         desc, run_state, stop, progress, live_timing, lambda: acquire(rt, warn))
        if run_state.finished is not None:  # aborted or failed in a segment
            return run_state.finished
        _stop_device(device, close=False)
        if progress is not None:
            progress(1.0, "analysis")
        why = None
        try:
            run_state.results = protocol.analyze(run_state.data(0), meta)
        except UserError as exc:
            why = str(exc)
        except Exception as exc:  # noqa: BLE001 - a failed analysis must not lose a good recording
            why = f"{type(exc).__name__}: {exc}"
        if stop.is_set():  # asked to stop (a signal) while analysing: the run did not finish
            return run_state.finish("aborted", _stop_reason(stop, "stopped during the analysis"))
        if why is not None:  # never "success" without its results: the recording is kept
            run_state.results = {"error": f"analysis failed: {why}"}
            return run_state.finish("failed", f"recorded, but the analysis failed: {why}; the "
                                    "session is complete: re-analyse it", "analysis")
        return run_state.finish("success", "completed")
    except KeyboardInterrupt as exc:
        _stop_device(device, close=False)
        return run_state.finish("aborted", str(exc) or "interrupted (Ctrl-C)")
    except RecordingError as exc:  # the session cannot be written on: the device first
        _stop_device(device, close=False)
        return run_state.finish("failed", str(exc), "recording")
    except UserError as exc:
        _stop_device(device, close=False)
        run_state.finish("failed", str(exc))
        raise
    except Exception as exc:
        _stop_device(device, close=False)
        run_state.finish("failed", f"{type(exc).__name__}: {exc}",
                         "device" if isinstance(exc, DeviceError) else "error")
        raise
    finally:
        _stop_device(device, close=close)


def checks(protocol: ProtocolBase, rig, desc=None, simulated: bool = True,
           skip_commissioning: bool = False, **gate_words):
    """What a run checks before anything reaches the device, in one place for every caller
    (``run``; the window's pre-check line and Start): the plant its theory takes, the
    commissioning gate (``gate_words``: its message's ``remedy`` and ``where``) and the exact
    sampled stability check with the device's own delay (``device_delay.resolve``: the rig's
    measured one, else what the device declares), the device's Coulomb friction
    (``device_friction.resolve``, set as the protocol's ``device_friction`` for its plan and
    analysis). ``desc``: the device's ``DeviceDescription``; None before one is connected (a
    delay or friction the device would declare is then not known). Returns (plant, delay,
    the pre-check's report); UserError when refused."""
    if desc is not None and desc.cannot_act:  # never pulse a device that cannot act
        raise UserError(f"{protocol.name} drives a force, but {desc.cannot_act}")
    plant = protocol.plant(rig)
    commissioning.gate(protocol.vetted_ves(plant), rig, simulated, skip_commissioning, **gate_words)
    delay = device_delay.resolve(rig, desc)
    protocol.device_friction = device_friction.resolve(protocol, desc)
    return plant, delay, precheck(protocol, plant, rig, delay)


def _segments(device, protocol, rig, plant, check, delay, friction, safety, watchdog, desc,
              run_state, stop, progress, live_timing, realtime) -> dict:
    """Start record, descriptor, then the protocol's segments through the loop; returns the
    analysis metadata. A segment that aborts or fails finishes the run (``run_state.finished``).
    Each ``run_loop`` runs under ``realtime()`` (the protocol's work between segments does
    not); the start record says what the first was granted."""
    from labbench.loop.chain import HapticLoop, run_loop

    T = float(desc.sample_time_s)
    grant = realtime().__enter__()  # the first segment's, now: the start record says what it got
    run_state.realtime = grant.record
    try:
        start = records.start_record(
            rig.as_dict(), protocol.describe(), protocol.seed,
            device=asdict(desc), plant={"m": plant.m, "b": plant.b}, device_delay=delay.as_dict(),
            friction=friction.as_dict(), precheck=json_safe(check), safety=safety.as_dict(), watchdog=watchdog.as_dict(),
            realtime=run_state.realtime)
        run_state.uid = start["uid"]
        run_state.emit(start)
        run_state.emit(records.descriptor_record(T))
        for text in desc.details.get("warnings", ()):  # e.g. a fallback for a missing object
            run_state.emit(records.event_record(run_state.last_t, "device_warning", text))
        meta = {"fs": 1.0 / T, "T": T, "ve": protocol.ve.as_dict(), "plant": start["plant"],
                "rig": rig.as_dict(), "metres_per_count": rig.metres_per_count,
                "protocol": protocol.describe(), "force_hold": desc.force_hold,
                "device_kind": desc.kind,
                device_delay.META_KEY: delay.s, **friction.as_meta(), "segments": run_state.segments}
        total = max(int(protocol.n_samples), 1)
        gen = protocol.segments(plant)
        segment = next(gen)
        # the earlier segments' share of live_timing
        before = {"overruns": 0, "max_s": 0.0, "worst_t_s": None, "wall_s": 0.0}
        while True:
            first = run_state.n_samples

            def on_progress(n_done, n_total, _first=first, _label=segment.shown or segment.label):
                if progress is not None:
                    progress(min((_first + n_done) / total, 1.0), _label)

            def on_live(snap, _first=first):
                worse = snap["max_s"] > before["max_s"]
                live_timing({"n": _first + snap["n"],
                             "overruns": before["overruns"] + snap["overruns"],
                             "max_s": snap["max_s"] if worse else before["max_s"],
                             "worst_t_s": snap["worst_t_s"] if worse else before["worst_t_s"],
                             "wall_s": before["wall_s"] + snap["wall_s"],
                             "T_s": T, "paced": desc.paced})

            run_state.emit(records.event_record(
                run_state.last_t, "segment", segment.label, role=segment.role,
                ve=segment.ve.as_dict(), n_samples=len(segment.excitation),
                device_counters=run_state.counters()))
            grant = grant or realtime().__enter__()
            try:
                outcome = run_loop(device, HapticLoop(segment.ve, safety), segment.excitation,
                                   run_state.emit, stop=stop, progress=on_progress,
                                   first_page=len(run_state.pages),
                                   live=on_live if live_timing is not None else None,
                                   watchdog=watchdog)
            finally:
                grant.__exit__(None, None, None)
                grant = None
            t = outcome.timing
            if t.get("max_s", 0.0) > before["max_s"]:
                before.update(max_s=t["max_s"], worst_t_s=t.get("worst", {}).get("t_s"))
            before["overruns"] += t.get("overruns", 0)
            before["wall_s"] += t.get("wall_s", 0.0)
            run_state.segments.append({
                "label": segment.label, "role": segment.role, "ve": segment.ve.as_dict(),
                "start": first,
                "stop": run_state.n_samples, "status": outcome.status, "reason": outcome.reason,
                "timing": dict(t), "device_counters": run_state.counters(),
                "energy_max_j": outcome.stats.get("energy_max_j")})
            if outcome.status == "aborted":
                run_state.finish("aborted", _stop_reason(stop, outcome.reason))
                return meta
            if outcome.status in _FAILED and not (outcome.status == "tripped"
                                                   and segment.trip_expected):
                run_state.finish("failed", f"{outcome.status}: {outcome.reason}",
                                 _CAUSE[outcome.status])
                return meta
            try:
                segment = gen.send(SegmentOutcome(outcome.status, outcome.reason,
                                                  run_state.data(first)))
            except StopIteration:
                return meta
    finally:
        if grant is not None:  # a segment raised
            grant.__exit__(None, None, None)


class _Run(records.RecordRouter):
    """Fans records out, keeps the page data and segment table, writes the stop record once."""

    def __init__(self, consumers: list):
        self.consumers = consumers
        self.pages: list[dict] = []
        self.events: list[dict] = []
        self.segments: list[dict] = []
        self.results: dict = {}
        self.uid: str | None = None
        self.started = False
        self.finished: RunResult | None = None
        self.n_samples = 0
        self.last_t = 0.0
        self.realtime: dict | None = None  # labbench.loop.realtime.Grant.record of the segments
        self.counters: Callable[[], dict | None] = lambda: None  # the device's, now

    def emit(self, rec: dict) -> None:
        self(rec)
        for c in self.consumers:
            c(rec)

    def on_start(self, rec: dict) -> None:
        self.started = True

    def on_page(self, rec: dict) -> None:
        self.pages.append(rec["data"])
        t = rec["data"]["t"]
        self.n_samples += len(t)
        if len(t):
            self.last_t = float(t[-1])

    def on_event(self, rec: dict) -> None:
        self.events.append(rec)

    def data(self, first: int) -> dict[str, np.ndarray]:
        """Channels of every sample from index ``first`` on."""
        joined = records.concat_pages({"kind": records.PAGE, "data": d} for d in self.pages)
        return {k: v[first:] for k, v in joined.items()}

    def timing(self) -> dict:
        """Loop timing over all segments (``labbench.loop.timing.merge``), the real-time factor
        (simulated seconds per wall second) and what the OS granted (``realtime``)."""
        out = loop_timing.merge([s["timing"] for s in self.segments],
                                [s["start"] for s in self.segments])
        if out.get("wall_s"):
            out["realtime_factor"] = self.n_samples * out["T_s"] / out["wall_s"]
        if out and self.realtime is not None:
            out["realtime"] = self.realtime
        return json_safe(out)

    def finish(self, status: str, reason: str, cause: str | None = None) -> RunResult:
        if self.finished is None:
            timing = self.timing()
            if self.started and timing.get("paced") and timing.get("overruns"):
                # what the window's status bar showed, in the record (replay, report, sessions)
                self.emit(records.event_record(self.last_t, "loop_timing", loop_timing.summary(timing),
                                               overruns=timing["overruns"], max_s=timing.get("max_s")))
            if self.started:  # no stream without its start record (e.g. Ctrl-C in the precheck)
                self.emit(records.stop_record(status, reason, n_samples=self.n_samples,
                                              timing=timing, results=summarize(self.results),
                                              device_counters=self.counters(),
                                              **({"cause": cause} if cause else {})))
            self.finished = RunResult(status, reason, self.results, timing, self.uid,
                                      self.n_samples, cause)
        return self.finished


def device_counters(device) -> dict | None:
    """The device's link counters now (``StatusReporting``: stray frames, EMCY, late
    SYNCs, CRC errors, ...), for the segment table and the stop record; None without."""
    if not isinstance(device, StatusReporting):
        return None
    try:
        return json_safe(dict(device.status().link))
    except Exception:  # noqa: BLE001 - a record of counters must not end a run
        return None


def summarize(results: dict, max_len: int = 64):
    """The results without long arrays (for the stop record; the data are in the pages)."""
    if isinstance(results, dict):
        return {k: summarize(v, max_len) for k, v in results.items()
                if not (_is_seq(v) and len(v) > max_len)}
    if isinstance(results, (list, tuple)):
        return [summarize(v, max_len) for v in results]
    return json_safe(results)


def _is_seq(v) -> bool:
    return isinstance(v, (list, tuple, np.ndarray))


def _stop_reason(stop, fallback: str) -> str:
    """Why the run was stopped: a ``labbench.loop.interrupts.StopRequest`` says (e.g. the signal)."""
    return getattr(stop, "reason", "") or fallback or "stopped"


def _stop_device(device, close: bool, timeout: float = 1.0) -> None:
    """Force to zero, disable, optionally close; falls back to emergency_stop, never raises."""
    try:
        device.command(0.0)
        device.disable(timeout=timeout)
    except Exception:  # noqa: BLE001 - shutting down: the e-stop below is the fallback
        with contextlib.suppress(Exception):
            device.emergency_stop()
    if close:
        with contextlib.suppress(Exception):
            device.close()
