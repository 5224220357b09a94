"""The one haptic loop chain, used by the simulator, the real drivers and replay.

Per sample k (the exact sampled-data model of ``labbench.model.linear``, then the safety envelope):

    v[k]     = a v[k-1] + (1 - a) (x[k] - x[k-1]) / T,   a = exp(-w0 T)
    f_ve[k]  = K x[k] + B v[k]                           (applied during step k + n, td = n T)
    u[k]     = f_exo[k] - f_ve[k - n]                    (plant m x'' + b x' = f_exo - f_ve)
    command  = safety(u[k])

Safety, in this order: position window and velocity limit (trip: force zero at
once), enable gate (the device is enabled only at a sample k where every force
the delay line holds, f_exo[k] - f_ve[k-n .. k], is within
``enable_force_threshold_n`` of zero: the command now and the n after it, should
the handle stay put. Gating on u[k] alone would open at once when td > 0, the line
still holding the zeros of the sampled model's initial state, and K x[0] would
reach the command n samples later. Before the gate opens the command and the
applied excitation are zero; a device that applies nothing until it confirms it is
enabled, ``labbench.device.Enabling``, keeps the gate shut until then), force clamp, force-rate limit, energy observer (fades the
force to zero over ``energy_fade_s``, then trips). ``run_loop`` adds the watchdog
(no sample within ``watchdog_s``, or a paced loop period longer than it: force
zero, trip) and the stop request.

Energy observer: a passivity observer (Hannaford & Ryu, IEEE TRO 18(1), 2002) of
the VE port, in discrete form. Over step k-1 the display pushed the handle with
``-f_d`` (``f_d`` = excitation applied - command) through ``dx = x[k] - x[k-1]``.
The energy it generated beyond what a spring K legitimately stores and
returns, less what the device's nominal damping dissipates, is accumulated:

    E[k] = max(0, E[k-1] - f_d dx + K (x[k]^2 - x[k-1]^2) / 2 - b_nom dx^2 / T)

Flooring at zero stops a long passive stretch from banking credit against a
later instability. E grows steadily exactly when the rendered spring's delay
loss K (T/2 + td) outweighs the damping b_nom (the paper's stability condition).

Flags: ``labbench.loop.safety`` documents the bits of the "flags" channel.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import chain

import numpy as np

from labbench import records
from labbench.loop import timing as loop_timing
from labbench.device import DeviceFault, Enabling, RawReading
from labbench.errors import UserError
from labbench.loop.safety import (
    CLAMP,
    DEVICE,
    FADE,
    GATED,
    OVERRUN,
    RATE,
    SEQ_GAP,
    TRIPPED,
    SafetyConfig,
    WatchdogPolicy,
)
from labbench.model.ve import VirtualEnvironment

__all__ = ["HapticLoop", "LoopOutcome", "SafetyConfig", "run_loop"]


# Order of the values in a row returned by ``HapticLoop.advance`` = the page channels.
ROW = ("t", "seq", "position", "velocity", "ve_force", "excitation", "command", "flags")
if tuple(records.CHANNELS) != ROW:
    raise ImportError("labbench.records.CHANNELS changed: update labbench.loop.chain.ROW")


class HapticLoop:
    """Velocity estimate -> VE force -> delay line -> + excitation -> safety -> command.

    ``step(seq, t_s, position_m, excitation_n)`` returns the force to command for
    step k. ``advance`` takes the same arguments and returns the whole row
    ``(t, seq, position, velocity, ve_force, excitation, command, flags)``
    (``ROW``; ``excitation`` as applied during step k: zero while gated or
    tripped). The attributes ``velocity``, ``ve_force``, ``excitation``,
    ``command``, ``flags``, ``energy_j``, ``energy_max_j``, ``gate_open``,
    ``fading``, ``trip_name`` and ``trip_reason`` read the state after the last
    sample. The chain state lives in a closure: cell access is cheaper than
    attribute access, and this runs 1000 times a second (300 000 in the simulator).
    """

    def __init__(self, ve: VirtualEnvironment, safety: SafetyConfig):
        self.ve, self.safety = ve, safety
        self.advance, self.trip, self.regate, self._state = _chain(ve, safety)

    def step(self, seq: int, t_s: float, position_m: float, excitation_n: float) -> float:
        """One sample through the chain; returns the force to command for step k."""
        return self.advance(seq, t_s, position_m, excitation_n)[6]

    def __getattr__(self, name):  # only called for names not set in __init__
        state = self.__dict__.get("_state")
        if state is not None:
            values = state()
            if name in values:
                return values[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


def _chain(ve: VirtualEnvironment, s: SafetyConfig):
    """Closures (advance, trip, regate, state) of one loop; see HapticLoop and the module
    docstring. ``advance(..., hold=True)`` and ``regate(row)``: the device holds this
    sample's force at zero (still enabling), so the row is a gated one and the gate is
    shut again (it reopens by its own rule once the device applies force)."""
    a = ve.filter_pole
    c = (1.0 - a) / ve.T
    K, B = ve.K, ve.B
    line = [0.0] * (ve.delay_samples + 1)  # ring holding f_ve[k-n .. k]
    L = len(line)
    lo, hi = s.position_limits_m
    vmax, fmax = s.velocity_limit_m_s, s.force_limit_n
    dmax = s.force_rate_limit_n_per_s * ve.T
    emax, gate_n = s.energy_limit_j, s.enable_force_threshold_n
    dgain = ve.T / s.energy_fade_s
    bnom_T = s.nominal_damping_ns_m / ve.T
    j = 0
    xp = seqp = None  # x[k-1], seq[k-1]; None before the first sample
    v = f = e_app = u_prev = 0.0
    flags_last = 0
    energy = energy_max = 0.0
    gate_open = fading = False
    gain = 1.0
    trip_name, trip_reason = "", None

    def trip(name: str, reason: str) -> None:
        """Latch a trip (event ``name``, one-line ``reason``): zero force from the next step on."""
        nonlocal trip_name, trip_reason
        if trip_reason is None:
            trip_name, trip_reason = name, reason

    def state() -> dict:
        return {"velocity": v, "ve_force": f, "excitation": e_app, "command": u_prev,
                "flags": flags_last, "energy_j": energy, "energy_max_j": energy_max,
                "gate_open": gate_open, "fading": fading, "trip_name": trip_name,
                "trip_reason": trip_reason}

    def regate(row):
        nonlocal gate_open, e_app, u_prev, flags_last
        gate_open = False
        e_app = u_prev = 0.0
        flags_last = (row[7] & SEQ_GAP) | GATED
        return row[:5] + (0.0, 0.0, flags_last)

    def advance(seq, t_s, x, exc, hold=False):
        nonlocal j, xp, seqp, v, f, e_app, u_prev, flags_last, energy, energy_max
        nonlocal gate_open, fading, gain
        if xp is None:
            xp = x
        dx = x - xp
        flags = SEQ_GAP if seqp is not None and seq != seqp + 1 else 0
        seqp = seq
        v = a * v + c * dx
        f = K * x + B * v
        line[j] = f
        j += 1
        if j == L:
            j = 0
        # energy observer over the step that just ended (force applied then, dx)
        e = energy - (e_app - u_prev) * dx + 0.5 * K * (x * x - xp * xp) - bnom_T * dx * dx
        xp = x
        if e <= 0.0:
            e = 0.0
        elif e > energy_max:
            energy_max = e
            if e > emax:
                fading = True
        energy = e

        u = exc - line[j]  # f_exo[k] - f_ve[k-n]
        if not lo <= x <= hi:
            trip("position_limit", f"position {x:.4g} m outside the window [{lo:g}, {hi:g}] m")
        elif not -vmax <= v <= vmax:
            trip("velocity_limit", f"velocity estimate {v:.4g} m/s beyond the limit {vmax:g} m/s")
        if trip_reason is not None:
            e_app = u_prev = 0.0
            flags_last = flags | TRIPPED
            return (t_s, seq, x, v, f, 0.0, 0.0, flags_last)
        if not gate_open or hold:  # min/max over n + 1 floats, only until the gate opens
            if not hold and exc - gate_n <= min(line) and max(line) <= exc + gate_n:
                gate_open = True
            else:
                gate_open = False
                e_app = u_prev = 0.0
                flags_last = flags | GATED
                return (t_s, seq, x, v, f, 0.0, 0.0, flags_last)
        if u > fmax:
            u, flags = fmax, flags | CLAMP
        elif u < -fmax:
            u, flags = -fmax, flags | CLAMP
        du = u - u_prev
        if du > dmax:
            u, flags = u_prev + dmax, flags | RATE
        elif du < -dmax:
            u, flags = u_prev - dmax, flags | RATE
        if fading:
            gain -= dgain
            flags |= FADE
            if gain <= 0.0:
                trip("energy", f"energy observer: {energy_max:.4g} J generated > {emax:g} J;"
                               " force faded to zero")
                e_app = u_prev = 0.0
                flags_last = flags | TRIPPED
                return (t_s, seq, x, v, f, 0.0, 0.0, flags_last)
            u *= gain
        e_app = exc
        u_prev = u
        flags_last = flags
        return (t_s, seq, x, v, f, exc, u, flags)

    return advance, trip, regate, state


@dataclass
class LoopOutcome:
    """How a ``run_loop`` ended.

    ``status``: "completed", "tripped" (a safety trip or the watchdog zeroed the
    force), "aborted" (stop requested) or "fault" (the device failed).
    ``timing``: ``labbench.loop.timing.period_stats`` (period p50_s, p99_s, max_s,
    overruns = periods > 1.5 T on paced devices, histogram, the worst stall and
    when) plus wall_s and realtime_factor. ``stats``: counts of samples
    clamped / rate-limited / with sequence gaps, peak observer energy.
    """

    status: str
    reason: str
    n_done: int
    timing: dict
    stats: dict = field(default_factory=dict)


_LOUD = CLAMP | RATE | SEQ_GAP | DEVICE | FADE | TRIPPED  # bits that may need an event


def run_loop(device, loop: HapticLoop, excitation: np.ndarray, emit: records.Consumer,
             stop: threading.Event | None = None,
             progress: Callable[[int, int], None] | None = None,
             page_size: int = 100, first_page: int = 0,
             live: Callable[[dict], None] | None = None,
             watchdog: WatchdogPolicy | None = None) -> LoopOutcome:
    """Run ``len(excitation)`` samples of ``loop`` on ``device``; emit pages and events.

    The device is enabled here, at the sample where the enable gate opens, and
    is commanded to zero and disabled on every way out. ``stop`` may be set from
    any thread (GUI, Ctrl-C): the loop commands zero at its next sample and
    returns "aborted" (so does Ctrl-C in this thread, keeping the samples so far);
    for an emergency stop call ``device.emergency_stop()``
    first, which zeroes the force at the device at once. Pages are numbered from
    ``first_page`` (several runs can share one stream). Devices may offer
    ``read_raw(timeout) -> (seq, t_s, position_m, flags)`` as a fast form of
    ``read``. ``live(snapshot)``, if given, is called after each page with the
    timing so far: ``n`` samples, ``overruns``, ``max_s`` and ``worst_t_s``.
    ``watchdog``: ``labbench.loop.safety.WatchdogPolicy`` (default: the hardware's, from
    ``loop.safety.watchdog_s``; a simulator's records a late period and goes on).

    Steady state allocates nothing that outlives a page: the periods go to a
    list made before the loop, a page's rows are freed when it is emitted.
    """
    desc = device.describe()
    T = loop.ve.T
    if abs(desc.sample_time_s - T) > 1e-12 * T:
        raise UserError(f"VE sample time {T} s differs from the device's {desc.sample_time_s} s")
    if not 1 <= page_size <= 100_000:
        raise UserError(f"page_size must be 1..100000, got {page_size}")
    exc = np.asarray(excitation, dtype=float).tolist()
    n = len(exc)
    stop = stop or threading.Event()
    paced = bool(desc.details.get("paced", True))
    wd = loop.safety.watchdog_s
    policy = watchdog or WatchdogPolicy.for_device(loop.safety, simulated=False)
    read_timeout = policy.sample_timeout_s
    late = loop_timing.OVERRUN_T * T if paced else float("inf")
    too_late = policy.period_limit_s if paced else float("inf")

    if isinstance(device, RawReading):
        raw = device.read_raw
    else:
        def raw(timeout, _read=device.read):
            s = _read(timeout)
            return s.seq, s.t_s, s.position_m, s.flags

    rows: list[tuple] = []  # one ROW per sample of the page being filled
    periods = [0.0] * n  # wall time from the previous sample's arrival to this one's
    worst = [0.0, -1, None, None]  # longest period so far: seconds, sample, t_s, wall offset
    counts = {"clamp": 0, "rate": 0, "seq_gap": 0, "device_flags": 0, "overrun": 0}
    last_event_t: dict[str, float] = {}
    pages = [first_page, 0]  # next page index, rows emitted before the current ``rows``

    def event(t_s, name, reason, **extra):
        emit(records.event_record(t_s, name, reason, **extra))

    def flush():
        m = len(rows)
        if not m:
            return
        block = np.fromiter(chain.from_iterable(rows), float, m * len(ROW)).reshape(m, len(ROW))
        rows.clear()  # short-lived rows keep the garbage collector's work flat
        data = {name: block[:, c].copy() for c, name in enumerate(ROW)}
        data["seq"] = data["seq"].astype(np.int64)
        data["flags"] = data["flags"].astype(np.int64)
        emit(records.page_record(pages[0], data))
        pages[0] += 1
        pages[1] += m
        if progress is not None:
            progress(pages[1], n)
        if live is not None:
            live({"n": pages[1], "overruns": counts["overrun"], "max_s": worst[0],
                  "worst_t_s": worst[2], "wall_s": clock() - start})

    def last_event(t_s, name, reason):
        """The event that ends the run, after the samples that led to it."""
        flush()
        event(t_s, name, reason)

    def noisy(i, t_s, seq, flags):
        """Slow path: count saturations, emit events (clamp and rate at most once a second)."""
        for bit, key, name in ((CLAMP, "clamp", "force clamp engaged"),
                               (RATE, "rate", "force-rate limit engaged")):
            if flags & bit:
                counts[key] += 1
                if t_s - last_event_t.get(key, -1e300) >= 1.0:
                    last_event_t[key] = t_s
                    event(t_s, key, f"{name} (sample {i}, {counts[key]} so far)")
        if flags & SEQ_GAP:
            counts["seq_gap"] += 1
            event(t_s, "seq_gap", f"device skipped samples before seq {seq}")
        if flags & DEVICE:
            counts["device_flags"] += 1
        if flags & FADE and "fade" not in last_event_t:
            last_event_t["fade"] = t_s
            event(t_s, "energy", f"energy observer over {loop.safety.energy_limit_j:g} J:"
                                 " fading force to zero", energy_j=loop.energy_j)

    clock = time.perf_counter
    advance, command, stop_set, keep = loop.advance, device.command, stop.is_set, rows.append
    holding = device.holding if isinstance(device, Enabling) else None
    enabled = waiting = False  # waiting: enabled, the device not applying force yet
    status, reason, i = "completed", "", 0
    t_s = 0.0
    left = page_size
    start = prev = clock()
    try:
        for i in range(n):
            if stop_set():
                command(0.0)
                status, reason = "aborted", "stop requested"
                last_event(t_s, "stop", reason)
                break
            try:
                seq, t_s, x, dflags = raw(read_timeout)
            except TimeoutError:
                command(0.0)
                status, reason = "tripped", f"watchdog: no sample within {read_timeout:g} s"
                loop.trip("watchdog", reason)
                last_event(t_s, "watchdog", reason)
                break
            now = clock()
            d = periods[i] = now - prev
            prev = now
            extra = dflags and DEVICE
            if d > late and i:  # the first period includes starting the device
                extra |= OVERRUN
                counts["overrun"] += 1
                if d > too_late:
                    loop.trip("watchdog", f"watchdog: loop period {d * 1e3:.3g} ms"
                                          f" > {wd * 1e3:g} ms")
                elif d > wd and t_s - last_event_t.get("stall", -1e300) >= 1.0:
                    last_event_t["stall"] = t_s  # a simulator's: said, at most once a second
                    event(t_s, "stall", f"host stall: loop period {d * 1e3:.3g} ms > watchdog "
                                        f"{wd * 1e3:g} ms; simulator: recorded, run goes on")
                elif t_s - last_event_t.get("overrun", -1e300) >= 1.0:
                    last_event_t["overrun"] = t_s  # what the status bar counts, at most 1/s
                    event(t_s, "overrun", f"loop period {d * 1e3:.3g} ms > "
                                          f"{loop_timing.OVERRUN_T:g} T ({counts['overrun']} so "
                                          "far in this segment)")
            if d > worst[0] and i:
                worst[:] = d, i, t_s, now - start
            if waiting:
                waiting = holding()
                row = advance(seq, t_s, x, exc[i], waiting)
            else:
                row = advance(seq, t_s, x, exc[i])
            flags = row[7]
            if not enabled and not flags & (GATED | TRIPPED):
                device.enable(timeout=wd)
                enabled = True
                prev = clock()  # the enable call is not a loop overrun
                event(t_s, "enabled", f"enable gate opened at |force| = {abs(row[6]):.3g} N")
                if holding is not None and holding():  # this command will not be applied
                    waiting = True
                    row = loop.regate(row)
                    flags = row[7]
            command(row[6])
            if extra:
                flags |= extra
                row = row[:7] + (flags,)
            keep(row)
            if flags & _LOUD:
                noisy(i, t_s, seq, flags)
                if flags & TRIPPED:
                    status, reason = "tripped", loop.trip_reason
                    last_event(t_s, loop.trip_name, reason)
                    break
            left -= 1
            if not left:
                flush()
                left = page_size
    except DeviceFault as exc_:
        status, reason = "fault", f"device fault: {exc_}"
        _safe(device.emergency_stop)
        last_event(t_s, "device_fault", reason)
    except KeyboardInterrupt:  # Ctrl-C ends the loop like the stop event, samples kept
        _safe(lambda: device.command(0.0))
        status, reason = "aborted", "interrupted (Ctrl-C)"
        last_event(t_s, "stop", reason)
    finally:
        _safe(lambda: device.command(0.0))
        _safe(lambda: device.disable(timeout=wd))
    wall = clock() - start
    flush()
    done = pages[1]
    timing = loop_timing.period_stats(periods[1:done], T, paced, *worst[1:])
    timing.update(wall_s=wall, realtime_factor=done * T / wall if wall > 0 else float("inf"))
    stats = {**counts, "energy_max_j": loop.energy_max_j, "pages": pages[0] - first_page}
    return LoopOutcome(status, reason or "", done, timing, stats)


def _safe(call) -> None:
    """Best effort on the way out: a failing device must not mask the first error."""
    try:
        call()
    except Exception:  # noqa: BLE001, S110 - shutting down; the outcome already says what failed
        pass
