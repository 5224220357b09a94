"""Work off the GUI thread: acquisition runs, replays and slow one-off jobs.

Every job is a plain ``threading.Thread`` (no Qt object lives on it) that puts
``(kind, payload)`` messages into a ``Mailbox``; the window drains the mailbox
from a QTimer. ``SimpleQueue.put`` never blocks, so the acquisition loop never
waits for the GUI however slow the drawing is.
"""
from __future__ import annotations

import logging
import queue
import threading
from typing import Callable

from labbench.device import DeviceFault
from labbench.errors import UserError
from labbench.records import START

log = logging.getLogger(__name__)


class Mailbox:
    """Thread-safe hand-over of messages to the GUI thread."""

    def __init__(self):
        self._q: queue.SimpleQueue = queue.SimpleQueue()

    def put(self, kind: str, payload=None) -> None:
        self._q.put((kind, payload))

    def drain(self, limit: int = 10_000) -> list[tuple[str, object]]:
        """Everything waiting (at most ``limit`` messages), without blocking."""
        out = []
        try:
            while len(out) < limit:
                out.append(self._q.get_nowait())
        except queue.Empty:
            pass
        return out


def describe_error(exc: BaseException) -> str:
    """One line a person can act on; unexpected errors keep their type name."""
    if isinstance(exc, UserError):
        return str(exc)
    if isinstance(exc, DeviceFault):
        return f"device fault: {exc}"
    if isinstance(exc, TimeoutError):
        return f"timed out: {exc}" if str(exc) else "timed out waiting for the device"
    return f"{type(exc).__name__}: {exc}"


def run_in_background(mailbox: Mailbox, tag: str, fn: Callable, *args, **kwargs) -> threading.Thread:
    """Run ``fn`` on a daemon thread; post ("result", (tag, value)) or ("error", (tag, msg))."""

    def body():
        try:
            value = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the window, never raised into Qt
            if not isinstance(exc, (UserError, DeviceFault, TimeoutError)):
                log.exception("background job %s failed", tag)
            mailbox.put("error", (tag, describe_error(exc)))
        else:
            mailbox.put("result", (tag, value))

    thread = threading.Thread(target=body, name=f"labbench-{tag}", daemon=True)
    thread.start()
    return thread


def start_run(mailbox: Mailbox, device, protocol, rig, stop: threading.Event,
              session_dir=None, start_extra: dict | None = None) -> threading.Thread:
    """Run ``protocol`` on ``device`` through the runner on its own thread.

    Records go to the mailbox (as ("record", rec)) and, when ``session_dir`` is
    given, to a crash-safe session file whose start record also carries
    ``start_extra`` (the runner has no such field, so it is added on the way to
    the file); progress as ("progress", (frac, text)); the end as
    ("result", ("run", RunResult)) or ("error", ("run", message)).
    """

    def job():
        from labbench.runner import run

        consumers = [lambda rec: mailbox.put("record", rec)]
        writer = None
        if session_dir is not None:
            from labbench.session import SessionWriter

            writer = SessionWriter(session_dir)

            def record(rec, _write=writer):
                _write({**rec, **start_extra} if start_extra and rec.get("kind") == START else rec)

            consumers.insert(0, record)
        try:
            # close=False: the device stays connected in the window for the next run
            return run(device, protocol, consumers, stop=stop, rig=rig, close=False,
                       progress=lambda frac, text: mailbox.put("progress", (frac, text)))
        finally:
            if writer is not None:
                writer.close()
                if writer.path is not None:  # None when the run was refused before its start record
                    mailbox.put("session", str(writer.path))

    return run_in_background(mailbox, "run", job)


def start_replay(mailbox: Mailbox, path, speed: float | None, stop: threading.Event) -> threading.Thread:
    """Read a session back into the mailbox as the same record stream
    (``labbench.session.replay``: ``speed`` 1.0 = real time, None = as fast as it reads)."""

    def job():
        from labbench.session import replay

        reader = replay(path, [lambda rec: mailbox.put("record", rec)], speed=speed, stop=stop)
        if reader.problem:
            mailbox.put("warning", f"replay: {reader.problem}")
        return "stopped" if stop.is_set() else "completed"

    return run_in_background(mailbox, "replay", job)
