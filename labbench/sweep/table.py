"""A sweep's table: a folder of Parquet part files, one row per point, written as rows come.

Layout of ``NAME.sweep/``::

    _spec.json            the spec of the last sweep into it (labbench.sweep.spec, as data)
    part-*.parquet        rows, appended in parts

Rows are buffered and written as a new part every ``flush_rows`` rows or
``flush_s`` seconds, each part through a temporary file renamed into place when
whole (``labbench.safe_write``), so a sweep stopped at any moment (Ctrl-C,
SIGTERM, a kill) leaves only whole parts and loses at most the rows of the buffer,
which a rerun computes again. Dot and underscore files are ignored by Parquet
readers, so ``pandas.read_parquet("NAME.sweep")`` or ``pyarrow.dataset`` read the
folder as one table too (``read_table`` also drops the duplicate rows a compaction
cut short may leave).
"""
from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from labbench.errors import UserError
from labbench.safe_write import output_folder, replacing

SPEC_FILE = "_spec.json"
PART_GLOB = "part-*.parquet"
SUFFIX = ".sweep"


def parts(directory) -> list[Path]:
    return sorted(Path(directory).glob(PART_GLOB))


def is_table(directory) -> bool:
    d = Path(directory)
    return d.is_dir() and ((d / SPEC_FILE).is_file() or bool(parts(d)))


def open_table(directory) -> Path:
    """``directory`` as a sweep table folder (created if missing, its parent must exist);
    refuses a folder holding anything else."""
    d = Path(directory)
    if d.exists() and d.is_dir() and any(d.iterdir()) and not is_table(d):
        raise UserError(f"{d} is not a sweep table (no {SPEC_FILE}, no part files): "
                        "give a new or a sweep folder")
    return output_folder(d)


def write_spec(directory, spec_dict: dict) -> None:
    with replacing(Path(directory) / SPEC_FILE, force=True) as tmp:
        tmp.write_text(json.dumps(spec_dict, indent=1, sort_keys=True))


def read_spec(directory) -> dict:
    p = Path(directory) / SPEC_FILE
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise UserError(f"{directory}: no {SPEC_FILE}: not a sweep table") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{p}: unreadable ({exc})") from None


class TableWriter:
    """Appends rows; each flush is one new part file. ``close()`` flushes (safe twice)."""

    def __init__(self, directory, flush_rows: int = 64, flush_s: float = 10.0,
                 clock=time.monotonic):
        self.directory = Path(directory)
        self.flush_rows, self.flush_s, self._clock = flush_rows, flush_s, clock
        self._rows: list[dict] = []
        self._last = clock()
        self._n = 0
        self.written = 0

    def append(self, row: dict) -> None:
        self._rows.append(row)
        if len(self._rows) >= self.flush_rows or self._clock() - self._last >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        self._last = self._clock()
        if not self._rows:
            return
        table = rows_table(self._rows)
        self._n += 1
        name = f"part-{time.time_ns():x}-{os.getpid()}-{self._n:04d}.parquet"
        with replacing(self.directory / name) as tmp:
            pq.write_table(table, tmp)
        self.written += len(self._rows)
        self._rows = []

    def close(self) -> None:
        self.flush()


def rows_table(rows: list[dict]) -> pa.Table:
    """Rows (dicts of scalars, not all with the same keys) as one Arrow table."""
    names = list(dict.fromkeys(k for r in rows for k in r))
    return pa.table({k: _column([r.get(k) for r in rows]) for k in names})


def _column(values: list) -> pa.Array:
    try:
        return pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError):  # mixed kinds: as text
        return pa.array([None if v is None else str(v) for v in values], pa.string())


def done_keys(directory) -> set[str]:
    """Keys of the rows already in the table (reads the key column only)."""
    keys: set[str] = set()
    for p in parts(directory):
        keys.update(pq.read_table(p, columns=["key"])["key"].to_pylist())
    return keys


def read_table(directory) -> pa.Table:
    """Every row of the table, one per key (the first written), sorted by point index."""
    tables = [pq.read_table(p) for p in parts(directory)]
    if not tables:
        return pa.table({})
    table = pa.concat_tables(_unified(tables), promote_options="permissive")
    seen, keep = set(), []
    for i, k in enumerate(table["key"].to_pylist()):
        if k not in seen:
            seen.add(k)
            keep.append(i)
    table = table.take(keep)
    return table.sort_by("index")


def _unified(tables: list[pa.Table]) -> list[pa.Table]:
    """Parts whose column types disagree beyond null and number widths get that column as text."""
    kinds: dict[str, set] = {}
    for t in tables:
        for f in t.schema:
            if not pa.types.is_null(f.type):
                kinds.setdefault(f.name, set()).add(
                    "number" if pa.types.is_integer(f.type) or pa.types.is_floating(f.type)
                    else str(f.type))
    text = {name for name, k in kinds.items() if len(k) > 1}
    return [_as_text(t, text) for t in tables] if text else tables


def _as_text(t: pa.Table, names: set) -> pa.Table:
    for c in names & set(t.column_names):
        t = t.set_column(t.schema.get_field_index(c), c, t[c].cast(pa.string()))
    return t


def compact(directory) -> None:
    """Merge the parts into one (written first, then the old parts removed: a stop between
    the two leaves duplicates that ``read_table`` drops)."""
    old = parts(directory)
    if len(old) < 2:
        return
    table = read_table(directory)
    name = f"part-{time.time_ns():x}-{os.getpid()}-all.parquet"
    with replacing(Path(directory) / name) as tmp:
        pq.write_table(table, tmp)
    for p in old:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def to_csv(directory, path, force: bool = False) -> Path:
    """The table as CSV (one header row, one line per point)."""
    import pyarrow.csv as pcsv

    table = read_table(directory)
    with replacing(path, force=force) as tmp:
        pcsv.write_csv(table, tmp)
    return Path(path)


def column(table: pa.Table, name: str) -> list:
    if name not in table.column_names:
        raise UserError(f"the table has no column {name!r}; columns: "
                        f"{', '.join(table.column_names)}")
    return table[name].to_pylist()
