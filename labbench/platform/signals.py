"""The signals that end a command, as this platform has them.

SIGINT (Ctrl-C) and SIGTERM exist everywhere. A closed terminal is SIGHUP on POSIX; a
Windows console has no SIGHUP but sends Ctrl-Break as SIGBREAK, and closing the
console window, logging off or shutting down are console control events that the C
runtime does not turn into a signal: ``console_close`` catches those with
``SetConsoleCtrlHandler`` and delivers SIGBREAK to the main thread, then holds the
event (Windows ends the process when the handler returns, or after 5 s for a close)
until the process has exited its command, so the run still zeroes the force and closes
its session.
"""
from __future__ import annotations

import atexit
import contextlib
import signal
import threading
from collections.abc import Callable, Iterator

from labbench.platform import is_windows, missing

# The console events after which Windows ends the process (wincon.h).
CTRL_CLOSE_EVENT, CTRL_LOGOFF_EVENT, CTRL_SHUTDOWN_EVENT = 2, 5, 6
CLOSE_EVENTS = (CTRL_CLOSE_EVENT, CTRL_LOGOFF_EVENT, CTRL_SHUTDOWN_EVENT)
HOLD_S = 4.5  # Windows gives a close handler 5 s (SPI_GETHUNGAPPTIMEOUT's default)


def ending_signals() -> tuple[int, ...]:
    """SIGINT, SIGTERM and whichever of SIGHUP / SIGBREAK this platform has."""
    found = tuple(getattr(signal, n) for n in ("SIGHUP", "SIGBREAK") if hasattr(signal, n))
    if not found:
        missing("the hang-up signal (SIGHUP)",
                "a closed terminal ends the command without zeroing the force or closing "
                "its session; use Ctrl-C or SIGTERM")
    return (signal.SIGINT, signal.SIGTERM) + found


class _Exited:
    """Set when the interpreter exits: how long a console close is held."""

    def __init__(self):
        self.event = threading.Event()
        atexit.register(self.event.set)


_exited: _Exited | None = None


def close_event_handler(deliver: Callable[[], None], exited: threading.Event,
                        hold_s: float = HOLD_S) -> Callable[[int], bool]:
    """The console control handler's body: for a close event ``deliver()`` the signal and
    wait until ``exited`` (or ``hold_s``); True: handled. Other events (Ctrl-C, Ctrl-Break)
    are the C runtime's: False passes them on."""

    def handler(ctrl_type: int) -> bool:
        if ctrl_type not in CLOSE_EVENTS:
            return False
        deliver()
        exited.wait(hold_s)
        return True

    return handler


@contextlib.contextmanager
def console_close(kernel32=None) -> Iterator[None]:
    """On Windows, inside the block, a console close / log-off / shut-down is SIGBREAK to the
    main thread (see the module docstring). Elsewhere (and without ``kernel32``) nothing."""
    if kernel32 is None and not is_windows():
        yield
        return
    global _exited
    import _thread
    import ctypes

    if kernel32 is None:
        kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
    _exited = _exited or _Exited()
    body = close_event_handler(lambda: _thread.interrupt_main(signal.SIGBREAK), _exited.event)
    functype = getattr(ctypes, "WINFUNCTYPE", ctypes.CFUNCTYPE)  # CFUNCTYPE: a test's fake
    callback = functype(ctypes.c_int, ctypes.c_uint)(lambda t: int(body(t)))
    if not kernel32.SetConsoleCtrlHandler(callback, True):
        missing("the console close event", "closing the console window ends the command "
                "without zeroing the force or closing its session")
        yield
        return
    try:
        yield
    finally:
        kernel32.SetConsoleCtrlHandler(callback, False)
