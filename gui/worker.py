"""Work off the GUI thread: replays and slow one-off jobs (runs go to the acquisition
process, ``labbench.gui.acquisition``, which posts the same messages).

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

from labbench.errors import DeviceFault, LabbenchError

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
    if isinstance(exc, DeviceFault):
        return f"device fault: {exc}"
    if isinstance(exc, LabbenchError):
        return str(exc)
    if isinstance(exc, TimeoutError):
        return f"timed out: {exc}" if str(exc) else "timed out waiting for the device"
    return f"{type(exc).__name__}: {exc}"


def run_in_background(mailbox: Mailbox, tag: str, fn: Callable, *args, **kwargs) -> threading.Thread:
    """Run ``fn`` on a daemon thread; post ("result", (tag, value)) or ("error", (tag, msg))."""

    def body():
        try:
            value = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the window, never raised into Qt
            if not isinstance(exc, (LabbenchError, TimeoutError)):
                log.exception("background job %s failed", tag)
            mailbox.put("error", (tag, describe_error(exc)))
        else:
            mailbox.put("result", (tag, value))

    thread = threading.Thread(target=body, name=f"labbench-{tag}", daemon=True)
    thread.start()
    return thread


def start_replay(mailbox: Mailbox, path, speed: float | None, stop: threading.Event) -> threading.Thread:
    """Read a session back into the mailbox as the same record stream
    (``labbench.sessions.replay.replay``: ``speed`` 1.0 = real time, None = as fast as it reads),
    after ("replay length", its number of samples)."""

    def job():
        from labbench.sessions.replay import replay
        from labbench.sessions.session_catalogue import summarize

        mailbox.put("replay length", summarize(path).n_samples)  # for the progress bar
        reader = replay(path, [lambda rec: mailbox.put("record", rec)], speed=speed, stop=stop)
        if reader.problem:
            mailbox.put("warning", f"replay: {reader.problem}")
        return "stopped" if stop.is_set() else "completed"

    return run_in_background(mailbox, "replay", job)
