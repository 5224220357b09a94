"""SIGINT, SIGTERM and SIGHUP (SIGBREAK on Windows) end a command cleanly, whatever
disposition was inherited.

A process started with SIGINT ignored (``nohup``, a background job, some
launchers) would not stop on Ctrl-C, and the default action of SIGTERM (``kill``,
a service manager) and SIGHUP (a closed terminal) ends the process on the spot:
no force zero, no stop record. So the CLI and the GUI's acquisition process
install their own handlers for all three (the ones the platform has:
``labbench.platform.signals``; on Windows a closed console is SIGBREAK too):

* during a run (``stopping``) a signal only sets the run's ``StopRequest``; the
  loop sees it at the next sample, commands zero force, disables the device and
  the session is closed with an ``aborted`` stop record naming the signal;
* elsewhere (``raising``) it raises ``Interrupted``, a ``KeyboardInterrupt``, so
  half-written outputs are cleaned up on the way out.

Either way the process exits with ``128 + n``, the shell's convention for a
process ended by signal ``n``.
"""
from __future__ import annotations

import contextlib
import signal
from collections.abc import Callable, Iterator

from labbench.platform.signals import console_close, ending_signals


def interrupt_reason(signum: int) -> str:
    """``interrupted by SIGTERM``; SIGINT adds "(Ctrl-C)", SIGBREAK "(Ctrl-Break or console closed)"."""
    name = signal.Signals(signum).name
    how = {"SIGINT": " (Ctrl-C)", "SIGBREAK": " (Ctrl-Break or console closed)"}.get(name, "")
    return f"interrupted by {name}{how}"


class Interrupted(KeyboardInterrupt):
    """A signal ended the command outside a run; ``exit_code`` is 128 + its number."""

    def __init__(self, signum: int):
        super().__init__(interrupt_reason(signum))
        self.signum = signum
        self.exit_code = 128 + signum


class StopRequest:
    """Whether, and why, a run should stop: what ``labbench.runner.run`` takes as ``stop``.

    Unlike ``threading.Event`` it takes no lock, so a signal handler may set it
    even when it interrupted the main thread inside another call on it. The
    first ``set`` wins the reason.
    """

    def __init__(self):
        self._set = False
        self.reason = ""
        self.signum: int | None = None

    def set(self, reason: str = "stop requested", signum: int | None = None) -> None:
        if not self._set:
            self.reason, self.signum = reason, signum
            self._set = True

    def is_set(self) -> bool:
        return self._set

    @property
    def exit_code(self) -> int | None:
        """128 + n when a signal set it, else None."""
        return None if self.signum is None else 128 + self.signum


@contextlib.contextmanager
def handle_signals(on_signal: Callable[[int], None]) -> Iterator[None]:
    """Call ``on_signal(signum)`` for SIGINT, SIGTERM and SIGHUP or SIGBREAK (an inherited
    SIG_IGN included) inside the block; the previous handlers come back afterwards. Main
    thread only."""
    previous = {s: signal.signal(s, lambda signum, _frame: on_signal(signum))
                for s in ending_signals()}
    try:
        with console_close():
            yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


def _raise(signum: int) -> None:
    raise Interrupted(signum)


def raising() -> contextlib.AbstractContextManager:
    """Inside the block a signal raises ``Interrupted``."""
    return handle_signals(_raise)


def stopping(stop: StopRequest) -> contextlib.AbstractContextManager:
    """Inside the block a signal sets ``stop`` (naming the signal); later signals add nothing,
    so the shutdown they asked for is not itself interrupted."""
    return handle_signals(lambda signum: stop.set(interrupt_reason(signum), signum))
