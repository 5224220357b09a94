"""Run a campaign: its points one after another on one device, a row each, resumable, in a
table shared as a sweep's is.

``run_campaign(plan, table_dir, run_point, stop)`` writes the table of a sweep
(``labbench.sweep.table``: ``_spec.json``, Parquet parts) with a sweep's discipline: the table
says what made it (a campaign on this device and rig; another kind, device or rig is refused
in one line), damaged parts are named in one line and, with ``repair``, set aside and their
points run again on this device; every point is claimed under the table's lock before it runs
(``labbench.sweep.sharing``), so two campaigns into one table never run a point twice (before,
both ran every point and the second one's sessions were in no row); on real hardware the
second one is refused (one rig, one campaign). Before the first point the charts are checked
(``check_charts``). Then every point whose key is not in the table, in the spec's order,
planned as it comes (``labbench.campaign.plan``):

* a point whose settings cannot be made, or that the pre-check called unstable, becomes its
  row at once (status ``refused`` or ``skipped``);
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

Points another campaign of the table claimed are left to it and waited for at the end (a
claim whose campaign died is taken over). So no point is lost (every finished point is a
row before the next starts) and none runs twice (a row's key is never run again, a claimed
one never run by another); ``Summary`` counts what happened.
"""
from __future__ import annotations

import difflib
import itertools
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from labbench import records
from labbench.campaign import plan as plans
from labbench.campaign import rows
from labbench.errors import UnstableVEError, UserError
from labbench.readout.escape import one_line
from labbench.safe_write import replacing, usable_folder
from labbench.sweep import sharing, table as tables
from labbench.sweep.point import typed_row

ATTEMPTS_FILE = "_attempts.json"
HARDWARE_HOLD = "_hardware"
PAUSE_POLL_S = 0.05
CHUNK = 64  # points whose keys are looked up in the table at a time
TICK_S = 2.0  # progress while passing points already in the table


@dataclass
class Progress:
    """What a progress callback hears: whole points and the fraction of the running one."""

    done: int  # rows of this campaign's points in the table, as far as seen
    total: int
    point: str  # label of the point running (or last run)
    phase: str  # "start", "run" (the runner's progress), "done" (its row is written),
    # "scan" (passing points already in the table), "wait" (for another campaign's points),
    # "check" (the charts' columns, before the first point)
    fraction: float  # of the running point
    message: str
    elapsed_s: float
    eta_s: float | None  # at this campaign's rate so far


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
    not_ok: int = 0  # rows written now whose status is not ok (skipped and refused included)
    wall_s: float = 0.0
    sessions: list = field(default_factory=list)
    refused: int = 0  # rows written for points whose settings cannot be made
    by_others: int = 0  # points other campaigns of the table ran meanwhile
    repaired: list = field(default_factory=list)  # damaged parts set aside (``repair``)
    complete: bool = False  # every point of the spec is a row in the table

    def as_dict(self) -> dict:
        return {"table": str(self.table), "points": self.total, "already": self.already,
                "ran": self.ran, "skipped": self.skipped, "refused": self.refused,
                "rerun": self.rerun, "by_others": self.by_others, "not_ok": self.not_ok,
                "complete": self.complete, "interrupted": self.interrupted,
                "wall_s": self.wall_s, "sessions": [str(s) for s in self.sessions],
                "repaired": [str(p) for p in self.repaired]}


class Attempts:
    """``_attempts.json``: the runs of each point that did not finish (key -> list of
    {"session", "reason", "time"}), read again and rewritten whole (renamed into place) under
    the table's lock at each change: campaigns sharing the table add to one file."""

    def __init__(self, directory, share: sharing.Share):
        self.path = Path(directory) / ATTEMPTS_FILE
        self.share = share
        self.data = self._read()

    def _read(self) -> dict:
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            raise UserError(f"{self.path}: unreadable ({exc})") from None
        if not isinstance(data, dict):
            raise UserError(f"{self.path}: not an attempts file")
        return data

    def of(self, key: str) -> list[dict]:
        got = self.data.get(key)
        return [a for a in got if isinstance(a, dict)] if isinstance(got, list) else []

    def add(self, key: str, session, reason: str) -> None:
        with self.share.locked():
            self.data = self._read()
            self.data.setdefault(key, []).append(
                {"session": str(session) if session else None, "reason": reason,
                 "time": time.time()})
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
                 sleep: Callable[[float], None] = time.sleep, repair: bool = False,
                 warn: Callable[[str], None] | None = None) -> Summary:
    """Run ``plan``'s points not yet in ``table_dir`` (module doc): ``CampaignTable`` and
    its ``run`` in one call."""
    with CampaignTable(plan, table_dir, repair, progress, warn) as table:
        return table.run(run_point, stop, progress, confirm, sleep)


class CampaignTable:
    """A campaign's hold on its table, everything checked before a point runs: the table's
    kind, device and rig (``claim_identity``), its parts (damaged ones refused, or set aside
    with ``repair``: ``repaired``), on real hardware no other campaign running into it, and
    the charts' columns (``check_charts``; ``warn(line)`` hears what it could not decide).
    ``index``: the keys in the table (what ``describe`` counts as done). ``run`` runs the
    points; ``close`` lets go of the table."""

    def __init__(self, plan, table_dir, repair: bool = False, progress=None, warn=None):
        self.plan, self.t0 = plan, time.monotonic()
        self.made = not os.path.lexists(table_dir)  # removed again if no row goes into it
        self.directory = tables.open_table(table_dir)
        context = plan.context
        self.share = sharing.Share(self.directory)
        try:
            if not context.simulated and not self.share.hold(HARDWARE_HOLD):
                raise UserError(f"{self.directory}: another campaign on real hardware is "
                                "running into this table: one rig runs one campaign at a time")
            with self.share.locked():
                tables.claim_identity(self.directory, plans.identity(context),
                                      bool(self.share.others()))
                self.index = tables.KeyIndex(self.directory, verify=repair)
                self.repaired = []
                if self.index.damaged:
                    if not repair:
                        raise tables.DamagedTable(self.directory, self.index.damaged,
                                                  f"run on {context.device}")
                    self.repaired = tables.set_aside(self.directory, self.index.damaged)
                    self.index = tables.KeyIndex(self.directory)
                tables.write_spec(self.directory,
                                  {**plan.spec.as_dict(), "campaign": context.as_dict()})
            usable_folder(tables.charts_folder(self.directory))  # its figures and report go there
            check_charts(plan, self.directory, progress, warn)
        except BaseException:
            self.close()
            raise

    def run(self, run_point: Callable, stop, progress: Callable[[Progress], None] | None = None,
            confirm: Callable[[object], bool] | None = None,
            sleep: Callable[[float], None] = time.sleep) -> Summary:
        """Run the points not yet in the table (module doc); ``stop`` is a
        ``labbench.loop.interrupts.StopRequest`` (or ``threading.Event``) the caller sets on a
        signal or a stop button."""
        run = _Campaign(self.plan, self.directory, self.share, self.index, run_point, stop,
                        progress, confirm, sleep, self.t0)
        run.summary.repaired = self.repaired
        try:
            while True:  # a round: the points not done nor claimed; then those others left
                if not run.round() or not run.deferred:
                    break
                if not sharing.wait_for_others(self.share, stop, run.waiting):
                    run.summary.interrupted = _reason(stop, "stopped")
                    break
        finally:
            run.writer.close()
            run.summary.wall_s = time.monotonic() - self.t0
            run.summary.exit_code = getattr(stop, "exit_code", None)
        summary = run.summary
        summary.complete = summary.interrupted is None and run.done == summary.total
        summary.by_others = max(run.done - summary.already - summary.ran - summary.skipped
                                - summary.refused, 0)
        if summary.complete:
            with self.share.locked():
                tables.compact(self.directory)
        return summary

    def close(self) -> None:
        self.share.close()
        if self.made:
            tables.discard_unused(self.directory, (HARDWARE_HOLD,))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Campaign:
    """One campaign's pass over the spec's points (``round``), its writer and its counts."""

    def __init__(self, plan, directory, share, index, run_point, stop, progress, confirm,
                 sleep, t0):
        self.plan, self.share, self.index = plan, share, index
        self.run_point, self.stop, self.progress = run_point, stop, progress
        self.confirm, self.sleep, self.t0 = confirm, sleep, t0
        self.context = plan.context
        # a run's row is written at once (``_row``); rows of points that did not run (refused,
        # skipped) go in parts of up to 64, at least every 10 s
        self.writer = tables.TableWriter(directory, flush_rows=64, on_flush=share.release)
        self.attempts = Attempts(directory, share)
        self.summary = Summary(directory, plan.spec.count(), 0, 0, 0, 0, None)
        self.first_round, self.first_point = True, True
        self.done = self.deferred = self.ran_now = 0
        self._last = time.monotonic()  # of the last progress heard

    # -- progress
    def report(self, label: str, phase: str, fraction: float, message: str) -> None:
        self._last = time.monotonic()
        if self.progress is None:
            return
        elapsed = time.monotonic() - self.t0
        runs = self.ran_now + fraction
        eta = elapsed / runs * max(self.summary.total - self.done - fraction, 0.0) \
            if runs > 0 else None
        self.progress(Progress(self.done, self.summary.total, label, phase, fraction, message,
                               elapsed, eta))

    def waiting(self, n: int) -> None:
        self.report("", "wait", 0.0, f"waiting for {n} points another campaign of the table runs")

    def _tick(self) -> None:
        if time.monotonic() - self._last >= TICK_S:
            self.report("", "scan", 0.0, f"{self.done} of {self.summary.total} points in the "
                                         "table so far")

    # -- one pass
    def round(self) -> bool:
        """Every point of the spec not in the table nor claimed by another campaign, run;
        False when the campaign ended early (``summary.interrupted``)."""
        self.done = self.deferred = 0
        self.summary.total = self.plan.spec.count()
        seen: set[int] = set()  # keys as numbers: a random draw repeated is one point
        points = self.plan.spec.iter_points()
        while chunk := list(itertools.islice(points, CHUNK)):
            with self.share.locked():
                self.index.refresh()
                busy = self.share.others()
            for point in chunk:
                key = self.plan.key(point)
                if int(key, 16) in seen:
                    self.summary.total -= 1
                    continue
                seen.add(int(key, 16))
                if key in self.index:
                    self.done += 1
                    self.summary.already += self.first_round
                    continue
                if key in busy:
                    self.deferred += 1
                    continue
                if not self._claim(key):
                    continue
                if not self._point(point, key):
                    self.share.release([key])
                    return False
            self._tick()
        self.first_round = False
        return True

    def _claim(self, key: str) -> bool:
        """Claim ``key`` under the lock unless it was written or claimed meanwhile."""
        with self.share.locked():
            self.index.refresh()
            if key in self.index:
                self.done += 1
                self.summary.already += self.first_round
                return False
            if key in self.share.others():
                self.deferred += 1
                return False
            self.share.claim([key])
        return True

    def _point(self, point, key: str) -> bool:
        """Plan and run one claimed point to its row; False when the campaign ends here."""
        s, pp = self.summary, self.plan.plan_point(point)
        if pp.refused is not None:
            self._row(refused_row(pp, self.context))
            s.refused += 1
            return True
        if pp.skipped is not None:
            self._row(rows.skipped_row(pp, self.context))
            s.skipped += 1
            return True
        if self.stop.is_set():
            s.interrupted = _reason(self.stop, "stopped")
            return False
        if not self.first_point and not _pause(self.context.settings.pause_s, self.stop,
                                               self.sleep):
            s.interrupted = _reason(self.stop, "stopped")
            return False
        self.first_point = False
        if self.confirm is not None and not self.confirm(pp):
            s.interrupted = f"the operator stopped before {pp.label}"
            return False
        earlier = [a["session"] for a in self.attempts.of(key) if a.get("session")]
        peak = CommandPeak()
        t_point = time.monotonic()
        self.report(pp.label, "start", 0.0, "starting")
        try:
            result, session = self.run_point(
                pp, self.stop, lambda f, m, _l=pp.label: self.report(_l, "run", f, m), [peak])
        except UnstableVEError as exc:  # the runner's pre-check, with the device's delay
            row = rows.base_row(pp, self.context)
            row.update(status="refused", error=str(exc), attempts=len(earlier) + 1)
            self._row(typed_row(row), ran=True)
            s.ran += 1
            return True
        except Exception as exc:  # a device that did not open or run (a wrong port, a
            # dead bus): no row, the point runs again next time; raised to the caller
            self.attempts.add(key, None, f"{type(exc).__name__}: {exc}")
            s.interrupted = f"{pp.label}: {exc}"
            raise
        if session:
            s.sessions.append(session)
        if ends_campaign(result):
            self.attempts.add(key, session, result.reason)
            s.interrupted = f"{pp.label}: {result.status}: {result.reason}"
            return False
        row = rows.run_row(pp, self.context, result, session, _start_record(session), peak.peak,
                           earlier, time.monotonic() - t_point)
        self._row(row, ran=True)
        s.ran += 1
        s.rerun += bool(earlier)
        self.ran_now += 1
        self.report(pp.label, "done", 1.0, row["status"])
        return True

    def _row(self, row: dict, ran: bool = False) -> None:
        self.writer.append(row)  # its claim is released once it is written
        if ran:
            self.writer.flush()  # minutes of device time: a row before the next point starts
        self.done += 1
        self.summary.not_ok += row["status"] != "ok"


def refused_row(pp, context) -> dict:
    """The row of a point whose settings cannot be made (a sweep's ``refused`` row)."""
    p = pp.point
    return typed_row({"key": pp.key, "index": p.index, **p.tags, **p.params,
                      "params_json": json.dumps({"params": p.params, "tags": p.tags},
                                                sort_keys=True),
                      "status": "refused", "error": pp.refused, "session": None, "attempts": 0,
                      "earlier_sessions": None, "device": context.device,
                      "rig.name": context.rig.name})


def check_charts(plan, directory, progress=None, warn=None) -> None:
    """Every column the spec's charts name, before the first point: a parameter, a case
    group, a column the table has, or one a row of this campaign has (the first point's
    row without running it, then, for the results' columns, that point run on the plain
    simulator: no device time). One UserError naming the chart and the column; before, a
    chart naming a missing column was refused after every point had run."""
    from labbench.sweep.charts import columns_named

    charts = plan.spec.charts
    if not charts:
        return
    spec = plan.spec
    known = {*spec.fixed, *spec.grid, *spec.cases, *spec.ranges,
             *(k for cases in spec.cases.values() for _, p in cases for k in p)}
    known |= set(tables.column_names(directory))
    wanted = [(i, c) for i, chart in enumerate(charts, 1) for c in columns_named(chart)]
    if all(c in known for _, c in wanted):
        return
    pp = _first_runnable(plan)
    if pp is None:
        return  # no point will run: no chart to draw
    known |= set(rows.skipped_row(pp, plan.context))
    if all(c in known for _, c in wanted):
        return
    if progress is not None:
        progress(Progress(0, plan.spec.count(), pp.label, "check", 0.0,
                          "checking the charts' columns: the first point on the plain "
                          "simulator", 0.0, None))
    try:
        known |= set(dry_row(pp, plan.context))
    except Exception as exc:  # noqa: BLE001 - the check is a help: it must not stop a campaign
        if warn is not None:
            warn(f"the charts' result columns were not checked (the first point could not run "
                 f"on the simulator: {one_line(exc)})")
        return
    for i, c in wanted:
        if c not in known:
            near = difflib.get_close_matches(c, known, n=1, cutoff=0.6)
            hint = (f"did you mean {near[0]!r}?" if near else
                    f"its rows have {len(known)} columns: {', '.join(sorted(known)[:8])}, ...")
            raise UserError(f"{spec.source}: [[chart]] {i} names column {c!r}, which no row of "
                            f"this campaign has; {hint}")


def _first_runnable(plan):
    """The first point that will run (neither refused nor skipped), among the first few."""
    for point in itertools.islice(plan.spec.iter_points(), CHUNK):
        pp = plan.plan_point(point)
        if pp.refused is None and pp.skipped is None:
            return pp
    return None


def dry_row(pp, context) -> dict:
    """The row ``pp`` would have, from a run on the plain simulator (its columns)."""
    from labbench.registry import open_device
    from labbench.runner import run

    device = open_device("sim", pp.rig, **pp.device_options)
    peak = CommandPeak()
    result = run(device, pp.protocol, [peak], rig=pp.rig, simulated=True)
    return rows.run_row(pp, context, result, None, None, peak.peak, [], 0.0)


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
    from labbench.sessions.session_format import SessionReader

    if not session:
        return None
    with SessionReader(session, decode_pages=False) as reader:
        for rec in reader:
            if rec.get("kind") == records.START:
                return rec
    return None
