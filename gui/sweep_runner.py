"""A sweep run from the window: ``labbench.sweep.engine.run_sweep``, the engine of ``labbench
sweep``, in a child process (no Qt here).

The child runs the spec into its table exactly as the command line does (the same
workers, resuming, part files; Dask's local cluster, when asked for, is the child's),
and posts each row's progress back. Why a process: Dask's scheduler threads and a sweep
computed in this process would share the window's interpreter (its drawing stalls) and
its garbage (the window collects in the GUI thread only, ``labbench.gui.gc_policy``).
Cancel is the CLI's Ctrl-C: the rows finished are kept, and running the spec again
computes only the rest. If the window's process dies, the child stops the same way.
"""
from __future__ import annotations

import multiprocessing as mp
import queue
import threading
from dataclasses import asdict
from multiprocessing.connection import wait as wait_handles

from labbench.gui.acquisition import SharedFlag, main_module_hidden

CANCELLED = "cancelled in the window"
FILL_S = 1.0  # rows reach the table at least this often: the page's map fills in as they come


def limit_reached(limit: int) -> str:
    return f"the {limit} point{'s' if limit != 1 else ''} asked for ran"


def _child(spec_path: str, table: str, workers: int | None, messages, cancel,
           limit: int = 0) -> None:
    from labbench.gui.worker import describe_error
    from labbench.loop.interrupts import StopRequest
    from labbench.sweep.engine import run_sweep
    from labbench.sweep.spec import load_spec

    stop = StopRequest()

    def watch() -> None:  # the window's Cancel, or the window's process gone
        parent = mp.parent_process()
        while not stop.is_set():
            if cancel.wait(0.2):
                stop.set(CANCELLED)
            elif parent is not None and not parent.is_alive():
                stop.set("the window's process ended")

    threading.Thread(target=watch, name="sweep-cancel", daemon=True).start()

    def progress(p) -> None:
        messages.put(("progress", {**asdict(p), "eta_s": p.eta_s}))
        if limit and p.computed >= limit and not stop.is_set():  # as Cancel: the rest next Run
            stop.set(limit_reached(limit))

    try:
        summary = run_sweep(load_spec(spec_path), table, workers=workers, progress=progress,
                            stop=stop, flush_s=FILL_S)
        messages.put(("done", {**asdict(summary), "table": str(summary.table),
                               "reason": stop.reason}))
    except BaseException as exc:  # noqa: BLE001 - the window shows it in one line
        messages.put(("error", describe_error(exc)))
    finally:
        stop.set()


class SweepRun:
    """One sweep of spec ``spec_path`` into table ``table``: ``post(kind, payload)`` is
    called on a reader thread with ("progress", Progress as a dict), then ("done", Summary
    as a dict) or ("error", one line). ``workers``: as ``labbench sweep --workers`` (None:
    one per CPU; 0: in the child itself); ``limit``: stop (as Cancel) once that many points
    were computed (0: all; the points under way on other workers finish too)."""

    def __init__(self, spec_path, table, workers: int | None, post, limit: int = 0):
        ctx = mp.get_context("spawn")
        self.cancel_flag = SharedFlag(ctx)
        self._messages = ctx.Queue()
        self._post = post
        # not a daemon: a sweep on Dask starts worker processes of its own
        self.process = ctx.Process(target=_child, name="labbench-sweep",
                                   args=(str(spec_path), str(table), workers, self._messages,
                                         self.cancel_flag, limit))
        with main_module_hidden():
            self.process.start()
        self._reader = threading.Thread(target=self._forward, name="labbench-sweep-reader",
                                        daemon=True)
        self._reader.start()

    def _forward(self) -> None:
        ended = False
        while True:
            try:
                kind, payload = self._messages.get(timeout=0.2)
            except queue.Empty:
                if not self.process.is_alive():
                    if not ended:
                        self._post("error", f"the sweep process ended (exit code "
                                            f"{self.process.exitcode}) before it finished")
                    return
                continue
            except (EOFError, OSError, ValueError):
                return
            self._post(kind, payload)
            ended |= kind in ("done", "error")

    def cancel(self) -> None:
        """Stop after the rows under way (the finished ones are kept)."""
        self.cancel_flag.set()

    def close(self, timeout: float = 20.0) -> None:
        """Cancel and wait for the child (the window closing); terminate it if it hangs."""
        self.cancel()
        wait_handles([self.process.sentinel], timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
