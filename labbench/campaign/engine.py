"""Run a campaign: its points one after another on one device, a row each, resumable.

``run_campaign(plan, table_dir, run_point, stop)`` writes the table of a sweep
(``labbench.sweep.table``: ``_spec.json``, Parquet parts) and runs every point whose key is
not in it yet, in the spec's order:

* a point the plan skipped (the pre-check called it unstable) becomes its row at once;
* otherwise ``run_point(planned, stop, progress, consumers)`` runs it through the runner
  (the caller's: the CLI's is ``labbench run``'s own path) and returns (RunResult, session
  path). A run that ends on its own (success, or a safety trip it did not expect, or an
  analysis error: its row says so) is a row, written at once (one part file per row: a
  row on hardware is minutes of work); so is a point the runner's pre-check refuses once
  the device declared a delay the rig does not state (status ``refused``);
* a device that does not open or run (an exception) ends the campaign with no row for
  the point, raised to the caller;
* a run that was stopped (Ctrl-C, SIGTERM, the stop button, an E-STOP) or ended by a
  device fault ends the campaign: its session is kept and named in the table's
  ``_attempts.json`` (key -> the sessions of runs that did not finish, and why), it gets
  no row, so the next run of the same command runs it again and counts the attempt;
* between two points the force is already zero and the device closed (the runner does
  that on every way out); the campaign waits the rig's ``[campaign] pause_s`` before the
  next one opens it, and asks ``confirm(point)`` first when given (an operator's yes).

So no point is lost (every finished point is a row before the next starts) and none runs
twice (a row's key is never run again); ``Summary`` counts what happened.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from labbench import records
from labbench.campaign import rows
from labbench.errors import UnstableVEError, UserError
from labbench.safe_write import replacing
from labbench.sweep import table as tables

ATTEMPTS_FILE = "_attempts.json"
PAUSE_POLL_S = 0.05


@dataclass
class Progress:
    """What a progress callback hears: whole points and the fraction of the running one."""

    done: int  # rows of this campaign's points in the table
    total: int
    point: str  # label of the point running (or last run)
    phase: str  # "start", "run" (the runner's progress), "done" (its row is written)
    fraction: float  # of the running point
    message: str
    elapsed_s: float
    eta_s: float | None  # at this campaign's rate so far (device time run vs planned)


@dataclass
class Summary:
    table: Path
    total: int
    already: int  # rows there before this run
    ran: int  # points run to a row now
    skipped: int  # rows written for points the pre-check skipped
    rerun: int  # of ``ran``, points an earlier run had left unfinished
    interrupted: str | None  # why the campaign ended early (None: it did not)
    exit_code: int | None = None  # a signal's 128 + n, when one stopped it
    not_ok: int = 0
    wall_s: float = 0.0
    sessions: list = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return self.interrupted is None and self.already + self.ran + self.skipped == self.total

    def as_dict(self) -> dict:
        return {"table": str(self.table), "points": self.total, "already": self.already,
                "ran": self.ran, "skipped": self.skipped, "rerun": self.rerun,
                "not_ok": self.not_ok, "complete": self.complete,
                "interrupted": self.interrupted, "wall_s": self.wall_s,
                "sessions": [str(s) for s in self.sessions]}


class Attempts:
    """``_attempts.json``: the runs of each point that did not finish (key -> list of
    {"session", "reason", "time"}), rewritten whole (renamed into place) at each change."""

    def __init__(self, directory):
        self.path = Path(directory) / ATTEMPTS_FILE
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            data = {}
        except (OSError, ValueError) as exc:
            raise UserError(f"{self.path}: unreadable ({exc})") from None
        if not isinstance(data, dict):
            raise UserError(f"{self.path}: not an attempts file")
        self.data = data

    def of(self, key: str) -> list[dict]:
        got = self.data.get(key)
        return [a for a in got if isinstance(a, dict)] if isinstance(got, list) else []

    def add(self, key: str, session, reason: str) -> None:
        self.data.setdefault(key, []).append(
            {"session": str(session) if session else None, "reason": reason, "time": time.time()})
        with replacing(self.path, force=True) as tmp:
            tmp.write_text(json.dumps(self.data, indent=1, sort_keys=True))


class CommandPeak:
    """A record consumer: the largest |command| [N] of the run's pages."""

    def __init__(self):
        self.peak: float | None = None

    def __call__(self, rec: dict) -> None:
        if rec.get("kind") == records.PAGE:
            c = rec["data"]["command"]
            if len(c):
                m = float(abs(c).max())
                self.peak = m if self.peak is None else max(self.peak, m)


def ends_campaign(result) -> bool:
    """A run that did not finish on its own: stopped, or its device faulted."""
    return result.status == "aborted" or (result.status == "failed"
                                          and result.reason.startswith("fault"))


def run_campaign(plan, table_dir, run_point: Callable, stop,
                 progress: Callable[[Progress], None] | None = None,
                 confirm: Callable[[object], bool] | None = None,
                 sleep: Callable[[float], None] = time.sleep) -> Summary:
    """Run ``plan``'s points not yet in ``table_dir`` (module doc); ``stop`` is a
    ``labbench.interrupts.StopRequest`` (or ``threading.Event``) the caller sets on a
    signal or a stop button."""
    t0 = time.monotonic()
    directory = tables.open_table(table_dir)
    tables.write_spec(directory, {**plan.spec.as_dict(), "campaign": plan.context.as_dict()})
    done = tables.done_keys(directory)
    ours = {p.key for p in plan.points}
    attempts = Attempts(directory)
    writer = tables.TableWriter(directory, flush_rows=1)
    summary = Summary(directory, len(plan.points), len(done & ours), 0, 0, 0, None)
    todo = [p for p in plan.points if p.key not in done]
    planned_s = sum(p.est_s for p in todo if p.skipped is None)
    state = {"run_s": 0.0}  # device time of the points finished in this run

    def report(pp, phase, fraction, message):
        if progress is None:
            return
        elapsed = time.monotonic() - t0
        ran = state["run_s"] + fraction * pp.est_s
        eta = elapsed / ran * max(planned_s - ran, 0.0) if ran > 0 else None
        progress(Progress(summary.already + summary.ran + summary.skipped, summary.total,
                          pp.label, phase, fraction, message, elapsed, eta))

    first = True
    try:
        for pp in todo:
            if stop.is_set():
                summary.interrupted = _reason(stop, "stopped")
                break
            if pp.skipped is not None:
                writer.append(rows.skipped_row(pp, plan.context))
                summary.skipped += 1
                continue
            if not first and not _pause(plan.context.settings.pause_s, stop, sleep):
                summary.interrupted = _reason(stop, "stopped")
                break
            first = False
            if confirm is not None and not confirm(pp):
                summary.interrupted = f"the operator stopped before {pp.label}"
                break
            earlier = [a["session"] for a in attempts.of(pp.key) if a.get("session")]
            peak = CommandPeak()
            t_point = time.monotonic()
            report(pp, "start", 0.0, "starting")
            try:
                result, session = run_point(pp, stop,
                                            lambda f, m, _pp=pp: report(_pp, "run", f, m), [peak])
            except UnstableVEError as exc:  # the runner's pre-check, with the device's delay
                row = rows.base_row(pp, plan.context)
                row.update(status="refused", error=str(exc), attempts=len(earlier) + 1)
                writer.append(rows.typed_row(row))
                summary.ran += 1
                continue
            except Exception as exc:  # a device that did not open or run (a wrong port, a
                # dead bus): no row, the point runs again next time; raised to the caller
                attempts.add(pp.key, None, f"{type(exc).__name__}: {exc}")
                summary.interrupted = f"{pp.label}: {exc}"
                raise
            if session:
                summary.sessions.append(session)
            if ends_campaign(result):
                attempts.add(pp.key, session, result.reason)
                summary.interrupted = f"{pp.label}: {result.status}: {result.reason}"
                break
            start = _start_record(session)
            row = rows.run_row(pp, plan.context, result, session, start, peak.peak, earlier,
                               time.monotonic() - t_point)
            writer.append(row)
            summary.ran += 1
            summary.rerun += bool(earlier)
            summary.not_ok += row["status"] != "ok"
            state["run_s"] += pp.est_s
            report(pp, "done", 1.0, row["status"])
    finally:
        writer.close()
        summary.wall_s = time.monotonic() - t0
        summary.exit_code = getattr(stop, "exit_code", None)
    if summary.complete:
        tables.compact(directory)
    return summary


def _pause(seconds: float, stop, sleep) -> bool:
    """Wait ``seconds`` unless a stop is asked first (False then)."""
    end = time.monotonic() + seconds
    while not stop.is_set():
        left = end - time.monotonic()
        if left <= 0:
            return True
        sleep(min(left, PAUSE_POLL_S))
    return False


def _reason(stop, fallback: str) -> str:
    return getattr(stop, "reason", "") or fallback


def _start_record(session) -> dict | None:
    """The start record of a session (what delay and plant its run used)."""
    from labbench.session_format import SessionReader

    if not session:
        return None
    with SessionReader(session, decode_pages=False) as reader:
        for rec in reader:
            if rec.get("kind") == records.START:
                return rec
    return None
