"""Run a sweep: the points not yet in the table, on Dask workers (or in this process), rows
streamed to the table as they come.

Workers: a ``distributed.LocalCluster`` of ``workers`` processes with one thread
each (default: one per CPU; BLAS and OpenMP held to one thread, so N workers use
N cores), or an existing cluster at ``scheduler`` (its workers need labbench
installed); ``workers=0`` computes in this process (no Dask at all). Each task
is ``labbench.sweep.point.compute_row(spec, point)``: pure, so a point's row
does not depend on which worker ran it, on how many there are, or on what ran
before it there (every random stream comes from the point's own seeds).

Memory stays bounded whatever the number of points: the spec's points are made as
they are needed (``Spec.iter_points``: a 10^6-point spec starts at once), at most
``window`` tasks are out at once, each finished row goes to the table's buffer
(``labbench.sweep.table.TableWriter``) and is written within ``flush_rows`` rows
or ``flush_s`` seconds, and no session is kept unless asked (``keep_sessions``). What
grows with the points is the set of their keys (about 100 bytes a point).

Sharing: the points are claimed in the table a few at a time
(``labbench.sweep.sharing``), so sweeps running at once into one table compute each
point once; a sweep that runs out of points waits for those the others claimed and
computes what they leave.

Stopping: ``stop`` (a ``labbench.loop.interrupts.StopRequest``: the CLI sets it on
SIGINT, SIGTERM or SIGHUP) is looked at twice a second; the tasks still out are
cancelled, the rows finished so far written, and the workers shut down. A rerun
skips the points already in the table (by key, ``labbench.sweep.spec``). The
local workers ignore the signals a terminal sends its whole foreground process
group (Ctrl-C, a hang-up: ``labbench.sweep.dask_worker``), so they end with the
sweep, not before it; and a task that did not finish (cancelled, or its worker
lost once the stop was asked) is no row: its point stays to compute.
"""
from __future__ import annotations

import contextlib
import itertools
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from labbench.errors import UserError
from labbench.sweep import sharing, table as tables
from labbench.sweep.point import compute_row
from labbench.sweep.spec import Point, Spec

# One thread per worker for the numeric libraries (a worker is one core's share).
WORKER_ENV = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                     "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")}
# Dask's statistical profiler samples each worker's task thread every 10 ms: CPU a sweep has
# no use for (and, seen here under load, a traceback of its own on stderr now and then).
# The nannies hand the workers this process's Dask configuration.
WORKER_DASK = {"distributed.worker.profile.enabled": False}
POLL_S = 0.5  # how often a running sweep looks at its stop request


@dataclass
class Progress:
    """What a progress callback hears after each row (and while waiting for other sweeps)."""

    done: int  # points of this spec in the table, as far as seen
    total: int  # points in the spec (a random draw repeated counts once, when met)
    failed: int  # rows of this run whose status is not "ok"
    computed: int  # rows computed by this run
    elapsed_s: float
    waiting: int = 0  # points other sweeps of the table are computing, waited for

    @property
    def eta_s(self) -> float | None:
        """Time left at this run's rate so far (None before its first row)."""
        if not self.computed:
            return None
        return self.elapsed_s / self.computed * (self.total - self.done)


@dataclass
class Summary:
    table: Path
    total: int
    before: int  # rows found in the table (written before, or by other sweeps meanwhile)
    computed: int
    failed: int
    wall_s: float
    stopped: bool
    workers: int
    repaired: list = field(default_factory=list)  # damaged parts set aside (--repair)
    error: str | None = None  # a part the system refused to write (the sweep stopped)


def run_sweep(spec: Spec, out, workers: int | None = None, scheduler: str | None = None,
              keep_sessions=None, progress: Callable[[Progress], None] | None = None,
              stop=None, flush_rows: int = 64, flush_s: float = 10.0,
              window: int | None = None, repair: bool = False) -> Summary:
    """Compute the points of ``spec`` missing from the table ``out`` (module doc), sharing
    it with any other sweep writing it (``labbench.sweep.sharing``). A damaged part is a
    ``DamagedTable`` error, or with ``repair`` set aside and its points computed again."""
    t0 = time.perf_counter()
    out = tables.open_table(out)
    check_names(spec)
    keep = None
    if keep_sessions is not None:
        from labbench.safe_write import output_folder

        keep = str(output_folder(keep_sessions).resolve())  # rows name sessions wherever read
    spec_d = spec.as_dict()
    with sharing.Share(out) as share:
        with share.locked():
            tables.claim_identity(out, tables.sweep_identity(spec), bool(share.others()))
            index = tables.KeyIndex(out, verify=repair)
            repaired = []
            if index.damaged:
                if not repair:
                    raise tables.DamagedTable(out, index.damaged)
                repaired = tables.set_aside(out, index.damaged)
                index = tables.KeyIndex(out)
            tables.write_spec(out, spec_d)
        state = Progress(0, spec.count(), 0, 0, 0.0)
        writer = tables.TableWriter(out, flush_rows, flush_s, on_flush=share.release)
        compute = _Compute(spec_d, keep, stop, workers, scheduler, window)
        claims = _Claims(spec, share, index, state)
        error = None
        try:
            while True:  # a round: the points not done nor claimed; then those others left
                claims.start_round()
                with contextlib.closing(compute.rows(iter(claims))) as rows:
                    for row in rows:
                        writer.append(row)
                        state.done += 1
                        state.computed += 1
                        state.failed += row["status"] != "ok"
                        state.elapsed_s = time.perf_counter() - t0
                        if progress is not None:
                            progress(state)
                writer.flush()
                if _stopping(stop) or not claims.deferred:
                    break
                if not _wait_for_others(share, state, stop, progress, t0):
                    break
        except tables.TableWriteError as exc:
            error = str(exc)
        finally:
            with contextlib.suppress(tables.TableWriteError):
                writer.close()
            compute.close()
        stopped = error is not None or state.done < state.total
        if not stopped:
            with share.locked():
                tables.compact(out)
    return Summary(out, state.total, state.done - state.computed, state.computed, state.failed,
                   time.perf_counter() - t0, stopped, compute.n_workers, repaired, error)


def _stopping(stop) -> bool:
    return stop is not None and stop.is_set()


class _Claims:
    """The points of ``spec`` this sweep computes, claimed in the table ``chunk`` at a time
    as they are asked for (``labbench.sweep.sharing``): not those in the table (counted as
    done), nor those another sweep claimed (``deferred``, for a later round), nor a point a
    random draw repeats."""

    def __init__(self, spec: Spec, share, index, state: Progress, chunk: int = 32):
        self.spec, self.share, self.index, self.state, self.chunk = spec, share, index, state, chunk
        self.deferred = 0

    def start_round(self) -> None:
        self.state.done, self.state.total, self.deferred = 0, self.spec.count(), 0

    def __iter__(self):
        seen: set[int] = set()  # keys as numbers
        batch = []
        for p in self.spec.iter_points():
            key = p.key(self.spec)
            if int(key, 16) in seen:
                self.state.total -= 1
                continue
            seen.add(int(key, 16))
            batch.append((p, key))
            if len(batch) >= self.chunk:
                yield from self._claim(batch)
                batch = []
        yield from self._claim(batch)

    def _claim(self, batch: list) -> list:
        with self.share.locked():
            self.index.refresh()
            busy = self.share.others()
            mine = []
            for p, key in batch:
                if key in self.index:
                    self.state.done += 1
                elif key in busy:
                    self.deferred += 1
                else:
                    mine.append((p, key))
            self.share.claim(key for _, key in mine)
        return mine


def _wait_for_others(share, state: Progress, stop, progress, t0: float) -> bool:
    """Wait until no other sweep has points claimed (``sharing.wait_for_others``), the
    progress said every 2 s; False when stopped meanwhile."""
    def tick(waiting: int) -> None:
        state.waiting = waiting
        state.elapsed_s = time.perf_counter() - t0
        if progress is not None:
            progress(state)

    done = sharing.wait_for_others(share, stop, tick, POLL_S)
    state.waiting = 0
    return done


class _Compute:
    """Rows of the points given, in this process (``workers == 0``) or on Dask (the client
    made at the first round with work, kept for the next, closed by ``close``)."""

    def __init__(self, spec_d: dict, keep, stop, workers, scheduler, window):
        self.spec_d, self.keep, self.stop = spec_d, keep, stop
        self.workers, self.scheduler, self.window = workers, scheduler, window
        self.client = None
        self.n_workers = 0

    def rows(self, todo):
        if self.workers == 0 and self.scheduler is None:
            return _inline(self.spec_d, todo, self.keep, self.stop)
        return self._dask(todo)

    def _dask(self, todo):
        todo = iter(todo)
        first = next(todo, None)  # no cluster for a round with nothing to compute
        if first is None:
            return
        if self.client is None:
            self.client, self.n_workers = _client(self.workers, self.scheduler)
            self.spec_f = self.client.scatter(self.spec_d, broadcast=True)
        yield from _on_dask(self.client, self.spec_f, itertools.chain([first], todo), self.keep,
                            self.stop, self.window or 4 * self.n_workers)

    def close(self) -> None:
        if self.client is not None:
            _close(self.client)
            self.client = None


def _inline(spec_d: dict, todo, keep, stop):
    for p, _key in todo:
        if _stopping(stop):
            return
        yield compute_row(spec_d, _task(p), keep)


def _task(p: Point) -> dict:
    return {"index": p.index, "params": p.params, "tags": p.tags}


def _client(workers: int | None, scheduler: str | None):
    """A Dask client: of the cluster at ``scheduler``, or of a new LocalCluster of processes
    (closed with the client). Returns (client, number of worker threads)."""
    level = logging.getLogger("distributed").level  # the CLI's (-v), before Dask configures it
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise UserError(f"labbench sweep needs dask[distributed]: {exc}") from None
    _quiet_dask(level)
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise UserError(f"no Dask scheduler answers at {scheduler}: {exc}") from None
        n = sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values())
        if n == 0:
            client.close()
            raise UserError(f"the Dask cluster at {scheduler} has no workers")
        return client, n
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise UserError(f"--workers must be at least 1 (0: in this process), got {n}")
    os.environ.update(WORKER_ENV)  # inherited by the worker processes the nannies start
    # no dashboard; the scheduler's other HTTP routes on a free port (its default, 8787,
    # taken by a second sweep on the machine, is a warning on stderr)
    import dask

    with dask.config.set(WORKER_DASK):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=None,
                               scheduler_kwargs={"dashboard_address": ":0"},
                               silence_logs=logging.ERROR, env=dict(WORKER_ENV),
                               preload=["labbench.sweep.dask_worker"])
    client = Client(cluster)
    client._labbench_cluster = cluster  # closed with the client (_close)
    return client, n


def _quiet_dask(level: int) -> None:
    """Importing distributed gives its loggers levels of their own (INFO) and a handler:
    "distributed" gets back the level it had (the CLI's -v sets it, as for the other
    libraries) and the others inherit it."""
    logging.getLogger("distributed").setLevel(level)
    for name in list(logging.root.manager.loggerDict):
        if name.startswith("distributed."):
            logging.getLogger(name).setLevel(logging.NOTSET)


def _close(client) -> None:
    cluster = getattr(client, "_labbench_cluster", None)
    with contextlib.suppress(Exception):
        client.close(timeout=10)
    if cluster is not None:
        with contextlib.suppress(Exception):
            cluster.close(timeout=10)


def _on_dask(client, spec_f, todo, keep, stop, window: int):
    """Rows of ``todo`` as the workers finish them, at most ``window`` tasks out at once.
    A task whose worker died (or that raised past compute_row) is a row with its error,
    unless it was cancelled or the sweep is stopping (then it is no row: see the module doc)."""
    from distributed import wait

    pending = iter(todo)
    running = {}

    def submit():
        for p, key in pending:
            f = client.submit(compute_row, spec_f, _task(p), keep, key=f"labbench-sweep-{key}")
            running[f] = (p, key)
            if len(running) >= window:
                return

    try:
        submit()
        while running:
            if _stopping(stop):
                return
            try:
                finished, _ = wait(list(running), timeout=POLL_S, return_when="FIRST_COMPLETED")
            except TimeoutError:
                continue
            for f in sorted(finished, key=lambda f: running[f][0].index):
                p, key = running.pop(f)
                row = _finished_row(f, p, key, stop)
                f.release()
                if row is not None:
                    yield row
            submit()
    finally:
        with contextlib.suppress(Exception):
            client.cancel(list(running))


def _finished_row(f, p: Point, key: str, stop) -> dict | None:
    from concurrent.futures import CancelledError

    from labbench.sweep.point import typed_row

    try:
        return f.result()
    except CancelledError:
        return None
    except Exception as exc:  # noqa: BLE001 - the worker, not the point, failed
        if stop is not None and stop.is_set():
            return None
        return typed_row({"key": key, "index": p.index, **p.tags, **p.params, "status": "error",
                          "error": f"worker: {type(exc).__name__}: {exc}"})


def check_names(spec: Spec, points=None) -> None:
    """Refuse a spec whose parameter names the targets do not know, before any point runs
    (a typo is one line, not ten thousand error rows): one point of every distinct set of
    names (``Spec.name_samples``, or of ``points``) is built, and for kind run its device
    opened and closed. Errors of a value are the point's own (its row says so)."""
    from labbench.sweep.point import analysis_params, build_run

    seen = set()
    for p in spec.name_samples() if points is None else points:
        names = frozenset(p.params)
        if names in seen:
            continue
        seen.add(names)
        try:
            if spec.kind == "analysis":
                analysis_params(spec.analysis, p.params)
                continue
            rig, _protocol, dev_opts, _truth = build_run(spec, p.params)
            from labbench.registry import open_device

            open_device(spec.device, rig, **dev_opts).close()
        except UserError as exc:
            if "unknown" in str(exc):
                raise UserError(f"{spec.source}: {exc}") from None
