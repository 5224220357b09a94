"""The acquisition process: the device, the runner and the session writer, away from Qt.

In one process, the GUI thread holds the GIL inside Qt/pyqtgraph drawing calls
for milliseconds at a time, and a 1 kHz loop on another thread of that process
misses its periods. So the device lives in a child process (``spawn``: nothing
of the GUI's state or Qt is inherited; this module imports no Qt) that opens
it, enables it, and runs protocols through ``labbench.runner.run_recorded`` (as
``labbench run`` does: real-time scheduling of the loop's thread, the session
recorded with ``labbench.sessions.session_format.SessionWriter``).

Pipes between the two (all put calls are non-blocking, so neither side ever
waits for the other):

* commands, GUI -> child: a ``multiprocessing.Queue`` of tuples;
* messages, child -> GUI: a ``multiprocessing.Queue`` of ``(kind, payload)``,
  the same messages ``labbench.gui.worker.Mailbox`` carries (records with their numpy
  page arrays pickled by multiprocessing, progress, results, errors as the one
  line ``labbench.gui.worker.describe_error`` makes), forwarded into the GUI's mailbox by
  a reader thread on the GUI side;
* E-STOP: a shared flag (``SharedFlag``); a thread of the child polls it every 2 ms
  and, the moment it is set, calls ``device.emergency_stop()`` and sets the
  run's stop event (the GUI never waits for the child to notice);
* Stop: a second shared flag, passed on to the run's stop event by the same thread;
* timing: the loop's overruns and worst stall so far, 4 times a second, for the status bar;
* watchdog: a child thread waits on the parent's process sentinel; if the GUI
  process dies the device is emergency-stopped, the run ends (its session
  closed with a stop record) and the child exits.
* signals: SIGINT, SIGTERM and SIGHUP (whatever disposition was inherited: a
  Ctrl-C in the terminal reaches the child too) stop the run like Stop, its
  session closed ``aborted`` naming the signal; then the device is closed and
  the child exits with 128 + n (``labbench.loop.interrupts``).
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import sys
import threading
import time
from multiprocessing.connection import wait as wait_handles

from labbench.device import StatusReporting
from labbench.loop.interrupts import StopRequest, handle_signals, interrupt_reason
from labbench.records import START

log = logging.getLogger(__name__)

HEALTH_PERIOD_S = 0.5
PARENT_GONE_GRACE_S = 3.0  # after the parent died: time for the run to end cleanly


def device_health(device) -> dict:
    """The device's ``status()`` as display strings (empty for a backend without one)."""
    if not isinstance(device, StatusReporting):
        return {}
    st = device.status()
    out = {"state": st.state, "fault": st.fault or "none"}
    if st.link:
        out["link"] = ", ".join(f"{k} {v}" for k, v in st.link.items() if v) or "all zero"
    return out


class SharedFlag:
    """A flag both processes see (one shared byte): set, clear and read never block.

    Not ``multiprocessing.Event``: its ``set()`` waits until every process waiting on it
    has woken, and a waiter that cannot wake (a daemon thread of a child that is exiting:
    Python freezes those) blocks it for ever; seen as a window whose close never returned,
    on a machine loaded enough that the child's exit outlasted the grace period."""

    def __init__(self, ctx):
        self._value = ctx.RawValue("b", 0)

    def set(self) -> None:
        self._value.value = 1

    def clear(self) -> None:
        self._value.value = 0

    def is_set(self) -> bool:
        return bool(self._value.value)

    def wait(self, timeout: float, poll_s: float = 0.002) -> bool:
        """True as soon as the flag is set (checked every ``poll_s``), False after ``timeout``."""
        deadline = time.monotonic() + timeout
        while not self.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            time.sleep(min(poll_s, left))
        return True


# ----- the child process ---------------------------------------------------------------------
class _Child:
    """State of the acquisition process: the open device and the run under way."""

    def __init__(self, commands, messages, estop, stop):
        self.commands, self.messages, self.estop, self.stop = commands, messages, estop, stop
        self.device = None
        self.run_stop = StopRequest()  # the stop request of the run under way
        self.signum: int | None = None  # the signal that ends this process
        self.lock = threading.Lock()  # the device reference, between the threads
        self.idle = threading.Event()  # no run under way
        self.idle.set()
        self._timing_sent = -1e9

    def post(self, kind: str, payload=None) -> None:
        self.messages.put((kind, payload))  # a feeder thread pickles and writes: never blocks

    def post_timing(self, snapshot: dict, every_s: float = 0.25) -> None:
        """The loop's timing so far, for the status bar: at most 4 a second."""
        now = time.monotonic()
        if now - self._timing_sent >= every_s:
            self._timing_sent = now
            self.post("timing", snapshot)

    # -- threads ----------------------------------------------------------------------------
    def watch_estop(self) -> None:
        """Zero the force the moment the shared E-STOP is set; pass Stop on to the run."""
        while True:
            if self.estop.wait(0.01):
                with self.lock:
                    dev = self.device
                self.run_stop.set("emergency stop (E-STOP)")
                if dev is not None:
                    try:
                        dev.emergency_stop()
                    except Exception as exc:  # noqa: BLE001 - reported, the run still stops
                        self.post("warning", f"device emergency_stop raised: {_describe(exc)}")
                self.post("estopped", dev is not None)
                while self.estop.is_set():  # latched until the GUI clears it (reconnect)
                    time.sleep(0.05)
            elif self.stop.is_set():
                self.run_stop.set()

    def watch_parent(self) -> None:
        """The backstop: the GUI process is gone -> force zero, run ended, exit."""
        parent = mp.parent_process()
        if parent is None:
            return
        wait_handles([parent.sentinel])  # returns when the parent process ends
        log.error("GUI process gone: emergency stop and exit")
        self.estop.set()
        self.run_stop.set("GUI process gone")
        self.idle.wait(PARENT_GONE_GRACE_S)  # the runner zeroes, disables, writes the stop record
        with self.lock:
            dev, self.device = self.device, None
        if dev is not None:
            try:
                dev.emergency_stop()
                dev.close()
            except Exception:  # noqa: BLE001 - exiting anyway
                log.exception("closing the device after the GUI process ended")
        os._exit(3)

    def report_health(self) -> None:
        while True:
            threading.Event().wait(HEALTH_PERIOD_S)
            with self.lock:
                dev = self.device
            if dev is None:
                continue
            try:
                health = device_health(dev)
            except Exception as exc:  # noqa: BLE001 - a health read failing is itself news
                health = {"state": f"health read failed: {_describe(exc)}"}
            self.post("health", health)

    # -- commands ------------------------------------------------------------------------------
    def on_signal(self, signum: int) -> None:
        """Signal handler (main thread): end the run under way; ``serve`` then exits."""
        self.signum = self.signum or signum
        self.run_stop.set(interrupt_reason(signum), signum)

    def serve(self) -> int:
        """Answer commands until "quit" (returns 0) or a signal (returns 128 + n)."""
        for body in (self.watch_estop, self.watch_parent, self.report_health):
            threading.Thread(target=body, name=f"acq-{body.__name__}", daemon=True).start()
        with handle_signals(self.on_signal):
            return self._serve()

    def _serve(self) -> int:
        while True:
            if self.signum is not None:
                self._close_device()
                return 128 + self.signum
            try:
                cmd, *args = self.commands.get(timeout=0.2)
            except queue.Empty:
                continue
            if cmd == "quit":
                self._close_device()
                return 0
            try:
                value = getattr(self, f"do_{cmd}")(*args)
            except BaseException as exc:  # noqa: BLE001 - reported to the window, never a crash
                from labbench.errors import LabbenchError

                if not isinstance(exc, (LabbenchError, TimeoutError)):
                    log.exception("acquisition command %s failed", cmd)
                self.post("error", (cmd, _describe(exc)))
            else:
                self.post("result", (cmd, value))

    def _close_device(self) -> None:
        with self.lock:
            dev, self.device = self.device, None
        if dev is not None:
            dev.close()

    def do_connect(self, opener, rig, options):
        self._close_device()
        dev = opener(rig, **options)
        with self.lock:
            self.device = dev
        if self.estop.is_set():  # pressed while connecting: latch this device too
            dev.emergency_stop()
        return dev.describe()

    def do_disconnect(self):
        self._close_device()

    def _dev(self):
        if self.device is None:
            from labbench.errors import UserError

            raise UserError("no device connected")
        return self.device

    def do_enable(self, timeout):
        self._dev().enable(timeout)

    def do_disable(self, timeout):
        self._dev().disable(timeout)

    def do_run(self, protocol_name, settings, rig, session_dir, start_extra, simulated,
               skip_commissioning=False):
        from labbench.loop.realtime import RealtimeConfig
        from labbench.registry import make_protocol
        from labbench.runner import run_recorded

        device = self._dev()
        self.idle.clear()
        self.run_stop = StopRequest()
        if self.signum is not None:  # arrived before this request existed
            self.run_stop.set(interrupt_reason(self.signum), self.signum)
        elif self.estop.is_set() or self.stop.is_set():
            self.run_stop.set()
        try:
            protocol = make_protocol(protocol_name, **settings)
            # close=False: the device stays connected in the window for the next run
            def forward(rec):  # the window sees the start record as it is written
                self.post("record", {**rec, **start_extra} if start_extra and rec["kind"] == START
                          else rec)

            return run_recorded(
                device, protocol, session_dir, [forward],
                start_extra=start_extra, on_session=lambda path: self.post("session", path),
                stop=self.run_stop, rig=rig, close=False, simulated=simulated,
                skip_commissioning=skip_commissioning,
                realtime=RealtimeConfig.from_rig(rig),
                progress=lambda frac, text: self.post("progress", (frac, text)),
                live_timing=self.post_timing,
                warn=lambda line: self.post("warning", line))[0]
        finally:
            self.idle.set()


def _describe(exc: BaseException) -> str:
    from labbench.gui.worker import describe_error

    return describe_error(exc)


def _child_main(commands, messages, estop, stop) -> None:
    """Entry point of the acquisition process."""
    logging.basicConfig(level=logging.WARNING)
    # the drivers turn a library's errors (canopen's SDO timeouts) into the window's one-line
    # messages; not also into lines of the terminal's (issue 43)
    logging.getLogger("canopen").propagate = False
    sys.exit(_Child(commands, messages, estop, stop).serve())


# ----- the GUI side ------------------------------------------------------------------------------
class Acquisition:
    """The GUI's handle on the acquisition process (started on first use).

    Methods only queue commands and return; answers arrive in ``mailbox`` as
    ("result", (cmd, value)) / ("error", (cmd, message)), plus ("record", rec),
    ("progress", (frac, text)), ("session", path), ("health", dict),
    ("estopped", bool) and ("acquisition died", exit code).
    """

    def __init__(self, mailbox):
        self.mailbox = mailbox
        ctx = mp.get_context("spawn")
        self._ctx = ctx
        self.estop = SharedFlag(ctx)
        self.stop = SharedFlag(ctx)
        self._commands = ctx.Queue()
        self._messages = ctx.Queue()
        self.process = None
        self._reader = None
        self._closing = False

    def _ensure_started(self) -> None:
        if self.process is not None and self.process.is_alive():
            return
        if self.process is not None:  # it died: its pipes may hold half a message
            self._close_queues()
            self._commands, self._messages = self._ctx.Queue(), self._ctx.Queue()
        self.process = self._ctx.Process(target=_child_main, name="labbench-acquisition", daemon=True,
                                         args=(self._commands, self._messages, self.estop, self.stop))
        with main_module_hidden():
            self.process.start()
        self._reader = threading.Thread(target=self._forward, args=(self.process, self._messages),
                                        name="labbench-acq-reader", daemon=True)
        self._reader.start()
        threading.Thread(target=self._watch, args=(self.process, self._reader),
                         name="labbench-acq-watch", daemon=True).start()

    def _close_queues(self) -> None:
        for q in (self._commands, self._messages):
            q.close()
            q.cancel_join_thread()

    def _forward(self, process, messages) -> None:
        """Child messages -> the GUI's mailbox, until the child has ended and sent all."""
        while True:
            try:
                kind, payload = messages.get(timeout=0.2)
            except queue.Empty:
                if not process.is_alive():
                    return
                continue
            except (EOFError, OSError, ValueError):  # ValueError: closed by shutdown
                return
            self.mailbox.put(kind, payload)

    def _watch(self, process, reader) -> None:
        """Says so when the child ends unasked: from its process handle, not from its pipe (a
        child killed in the middle of a message leaves the reader waiting for the rest)."""
        wait_handles([process.sentinel])
        reader.join(1.0)  # what it sent before it ended comes first
        if not self._closing:
            self.mailbox.put("acquisition died", process.exitcode)

    def send(self, *cmd) -> None:
        self._ensure_started()
        self._commands.put(cmd)

    def connect(self, opener, rig, options: dict) -> None:
        """Open a device in the child with ``opener(rig, **options)`` (picklable: a module-level
        function such as ``labbench.devices.open_device`` bound with functools.partial)."""
        self.estop.clear()  # a fresh device: the latch belongs to the one closed
        self.send("connect", opener, rig, options)

    def run(self, protocol_name: str, settings: dict, rig, session_dir, start_extra: dict | None,
            simulated: bool, skip_commissioning: bool = False):
        """``simulated``: the device is a simulator (``labbench.runner.run``: its watchdog
        records a host stall and the run goes on); ``skip_commissioning``: as the CLI's option
        (``labbench.commissioning.gate``)."""
        self.stop.clear()
        self.send("run", protocol_name, settings, rig,
                  None if session_dir is None else str(session_dir), start_extra, simulated,
                  skip_commissioning)

    def request_stop(self) -> None:
        self.stop.set()

    def emergency_stop(self) -> None:
        """Zero the force now: the child's e-stop thread is blocked on this event."""
        self.estop.set()

    def shutdown(self, timeout: float = 5.0) -> None:
        """Stop any run (force zeroed by the runner), close the device, end the child."""
        if self.process is None:
            return
        self._closing = True
        self.stop.set()
        if self.process.is_alive():
            self._commands.put(("quit",))
            self.process.join(timeout)
        if self.process.is_alive():  # a run that does not end: the e-stop, then terminate
            self.estop.set()
            self.process.join(1.0)
            self.process.terminate()
            self.process.join(1.0)
        self._close_queues()


class main_module_hidden:
    """``spawn`` re-imports the parent's ``__main__`` in the child (a script or ``-m gui...``
    that imports Qt); hide it while the child starts so the child imports only this module."""

    def __enter__(self):
        main = sys.modules["__main__"]
        self.main = main
        self.saved = {k: main.__dict__.pop(k) for k in ("__file__",) if k in main.__dict__}
        self.spec = getattr(main, "__spec__", None)
        main.__spec__ = None

    def __exit__(self, *exc):
        self.main.__dict__.update(self.saved)
        self.main.__spec__ = self.spec
