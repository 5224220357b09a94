"""A sweep's table: a folder of Parquet part files, one row per point, written as rows come.

Layout of ``NAME.sweep/``::

    _spec.json            the spec of the last sweep into it (labbench.sweep.spec, as data)
    _table.json           what made the table: a sweep or a campaign, its kind, device, rig
    part-*.parquet        rows, appended in parts
    _lock, _claims/       sweeps sharing the table (labbench.sweep.sharing)
    _damaged/             damaged parts set aside by ``--repair``

and the charts beside it, in ``NAME.charts/`` (not inside: Parquet readers take every
file of the folder for a part; a PNG there made ``pandas.read_parquet`` fail).

Rows are buffered and written as a new part every ``flush_rows`` rows or
``flush_s`` seconds, each part through a new file linked into place when whole
(``labbench.safe_write.new_output``), so a sweep stopped at any moment (Ctrl-C,
SIGTERM, a kill) leaves only whole parts and loses at most the rows of the buffer,
which a rerun computes again. Parts carry page checksums, so damage inside one is found
when it is read. Dot and underscore names are skipped by Parquet readers, so
``pandas.read_parquet("NAME.sweep")`` or ``pyarrow.parquet.read_table`` read the folder as
one table too (``read_table`` also drops the duplicate rows a merge cut short may leave).
A part that cannot be read (truncated, empty, garbled) is named in one line with the fix
(``--repair``: ``set_aside``).

One table holds one kind of rows: ``_table.json`` (written by the first sweep or campaign into
it, ``claim_identity``) says whether a sweep (its kind, run or analysis, and its simulator or
analysis) or a campaign (its device and rig) made it, and a command that would add another
kind, another device or another rig is refused in one line. Before, ``labbench sweep --repair``
on a campaign's table recomputed its points on a simulator beside the measured ones (4 rows
for 2 points), and a campaign into a sweep's table doubled every point.
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
from labbench.safe_write import new_output, output_folder, replacing, usable_folder

SPEC_FILE = "_spec.json"
IDENTITY_FILE = "_table.json"
PART_GLOB = "part-*.parquet"
SUFFIX = ".sweep"
CHARTS = ".charts"
DAMAGED = "_damaged"
_CHECKSUMS = {"write_page_checksum": True}
_VERIFY = {"page_checksum_verification": True}


def parts(directory) -> list[Path]:
    return sorted(Path(directory).glob(PART_GLOB))


def is_table(directory) -> bool:
    d = Path(directory)
    return d.is_dir() and ((d / SPEC_FILE).is_file() or bool(parts(d)))


def open_table(directory) -> Path:
    """``directory`` as a sweep table folder (created if missing, its parent must exist);
    refuses a folder holding anything else (dot and underscore names aside: a sweep that
    is starting has no more yet)."""
    d = usable_folder(directory)
    if d.is_dir() and not is_table(d) and any(not n.startswith((".", "_")) for n in os.listdir(d)):
        raise UserError(f"{d} is not a sweep table (no {SPEC_FILE}, no part files): "
                        "give a new or a sweep folder")
    return output_folder(d)


def charts_folder(directory) -> Path:
    """Where a table's charts go by default: ``NAME.charts`` beside ``NAME.sweep``."""
    d = Path(directory)
    return d.with_name(d.name.removesuffix(SUFFIX) + CHARTS)


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


def sweep_identity(spec) -> dict:
    """What a sweep of ``spec`` (``labbench.sweep.spec.Spec``) adds to a table."""
    return {"made_by": "sweep", "kind": spec.kind, "device": spec.device if spec.kind == "run"
            else None, "analysis": spec.analysis, "rig": None}


def describe_identity(ident: dict) -> str:
    """What made a table, in words."""
    if ident["made_by"] == "campaign":
        return f"a campaign's points measured on {ident['device']}, rig {ident['rig']!r}"
    if ident["kind"] == "analysis":
        return f"a sweep's {ident['analysis']} analyses of exact records"
    return f"a sweep's runs on the simulator {ident['device']}"


def _legacy_identity(directory: Path) -> dict | None:
    """A table written before ``_table.json``: what its ``_spec.json`` says made it."""
    try:
        spec = json.loads((directory / SPEC_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(spec, dict) or not isinstance(spec.get("sweep"), dict):
        return None
    sweep, campaign = spec["sweep"], spec.get("campaign")
    if isinstance(campaign, dict):
        return {"made_by": "campaign", "kind": "run", "device": campaign.get("device"),
                "analysis": None, "rig": campaign.get("rig")}
    kind = sweep.get("kind", "run")
    return {"made_by": "sweep", "kind": kind, "device": sweep.get("device", "sim")
            if kind == "run" else None, "analysis": sweep.get("analysis"), "rig": None}


def read_identity(directory) -> dict | None:
    """What made the table (``_table.json``, else inferred from an older table's spec), or
    None for a table nothing has written yet."""
    d = Path(directory)
    try:
        got = json.loads((d / IDENTITY_FILE).read_text())
    except FileNotFoundError:
        return _legacy_identity(d)
    except (OSError, ValueError) as exc:
        raise UserError(f"{d / IDENTITY_FILE}: unreadable ({exc})") from None
    if not isinstance(got, dict) or got.get("made_by") not in ("sweep", "campaign"):
        raise UserError(f"{d / IDENTITY_FILE}: not a table's identity")
    return got


def claim_identity(directory, ident: dict, in_use: bool = False) -> None:
    """Make ``ident`` the table's, or refuse in one line when another kind, device or rig made
    it. A table without rows takes the new one unless another is writing it (``in_use``: it
    holds claims). The caller holds the table's lock."""
    d = Path(directory)
    have = read_identity(d)
    if have is None or (not in_use and not parts(d)):
        with replacing(d / IDENTITY_FILE, force=True) as tmp:
            tmp.write_text(json.dumps(ident, indent=1, sort_keys=True))
    elif {k: have.get(k) for k in ident} != ident:
        fix = (f"its points run again only on {have['device']}: labbench campaign SPEC --device "
               f"{have['device']} --table {d} (with --repair for damaged parts)"
               if have["made_by"] == "campaign" else "give another table folder")
        raise UserError(f"{d} holds {describe_identity(have)}; this would add "
                        f"{describe_identity(ident)}: one table holds one kind of rows; {fix}")
    elif not (d / IDENTITY_FILE).exists():
        with replacing(d / IDENTITY_FILE, force=True) as tmp:  # an older table: said from now
            tmp.write_text(json.dumps(ident, indent=1, sort_keys=True))


class DamagedTable(UserError):
    """Part files that cannot be read; the message names them and the fix (``redo``: what the
    command does with their points: a sweep computes them, a campaign runs them)."""

    def __init__(self, directory, damaged: dict, redo: str = "compute"):
        self.damaged = dict(damaged)
        listed = [f"{p.name} ({why})" for p, why in list(self.damaged.items())[:3]]
        more = f" and {len(self.damaged) - 3} more" if len(self.damaged) > 3 else ""
        super().__init__(f"{directory}: {len(self.damaged)} damaged part file"
                         f"{'s' * (len(self.damaged) > 1)}: {', '.join(listed)}{more}; run the "
                         f"same command with --repair to move them to "
                         f"{Path(directory) / DAMAGED} and {redo} their points again")


def _damage(p: Path, exc: BaseException) -> str:
    try:
        if p.stat().st_size == 0:
            return "empty"
    except OSError:
        pass
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    if "magic bytes" in text or "footer" in text:
        return "truncated or not Parquet"
    if "checksum" in text.lower() or "corrupt" in text.lower():
        return "garbled: " + text[:60]
    return text[:80]


def _read_part(p: Path, columns=None) -> pa.Table:
    return pq.read_table(p, columns=columns, **_VERIFY)


_UNREADABLE = (pa.ArrowException, OSError, KeyError)  # a damaged part, as pyarrow says it


class KeyIndex:
    """The keys in a table's parts, each part read once (its key column; every column with
    ``verify``): ``refresh()`` reads the parts that appeared since. ``damaged``: the parts
    that cannot be read, with what is wrong."""

    def __init__(self, directory, verify: bool = False):
        self.directory, self.verify = Path(directory), verify
        self.keys: set[int] = set()  # as numbers: 60 bytes a key less than as text
        self.damaged: dict[Path, str] = {}
        self._read: set[str] = set()
        self.refresh()

    def refresh(self) -> None:
        for p in parts(self.directory):
            if p.name in self._read:
                continue
            self._read.add(p.name)
            try:
                table = _read_part(p, None if self.verify else ["key"])
                self.keys.update(int(k, 16) for k in table["key"].to_pylist())
            except FileNotFoundError:
                continue  # merged away meanwhile: its rows are in the merged part
            except _UNREADABLE as exc:
                self.damaged[p] = _damage(p, exc)

    def __contains__(self, key: str) -> bool:
        return int(key, 16) in self.keys


def set_aside(directory, damaged) -> list[Path]:
    """Move damaged parts into ``_damaged/`` (Parquet readers skip it); their points are no
    longer in the table, so a sweep computes them again. Returns where they went."""
    from labbench.safe_write import own_folder

    d = own_folder(Path(directory) / DAMAGED)
    moved = []
    for p in damaged:
        to = d / p.name
        n = 1
        while os.path.lexists(to):
            n += 1
            to = d / f"{p.stem}-{n}{p.suffix}"
        os.replace(p, to)
        moved.append(to)
    return moved


class TableWriteError(UserError):
    """A part that could not be written (full disk, ...): its rows are not in the table."""


class TableWriter:
    """Appends rows; each flush is one new part file, after which ``on_flush(keys)`` hears
    which keys are now in the table. ``close()`` flushes (safe twice). A part the system
    refuses is a ``TableWriteError`` (once: its rows are dropped, to compute again)."""

    def __init__(self, directory, flush_rows: int = 64, flush_s: float = 10.0,
                 clock=time.monotonic, on_flush=None):
        self.directory = Path(directory)
        self.flush_rows, self.flush_s, self._clock = flush_rows, flush_s, clock
        self._rows: list[dict] = []
        self._last = clock()
        self._on_flush = on_flush
        self.written = 0
        self.failed = False

    def append(self, row: dict) -> None:
        self._rows.append(row)
        if len(self._rows) >= self.flush_rows or self._clock() - self._last >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        self._last = self._clock()
        if not self._rows or self.failed:
            return
        rows, self._rows = self._rows, []
        table = rows_table(rows)
        try:
            with new_output(self.directory, f"part-{time.time_ns():x}-", ".parquet") as tmp:
                pq.write_table(table, tmp, **_CHECKSUMS)
        except UserError as exc:
            self.failed = True
            raise TableWriteError(f"{exc}; {self.written} rows written, the {len(rows)} "
                                  "after them not: run the same command again for them") from None
        self.written += len(rows)
        if self._on_flush is not None:
            self._on_flush([r["key"] for r in rows])

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


def discard_unused(directory, own: tuple = ()) -> None:
    """Remove a table folder this command made and wrote no row into (an operator who said
    no, a check that refused): its bookkeeping files (and the caller's ``own``), then the
    folder; anything else in it keeps it."""
    from labbench.sweep.sharing import CLAIMS, LOCK_FILE

    d = Path(directory)
    if parts(d):
        return
    for name in (LOCK_FILE, SPEC_FILE, IDENTITY_FILE, *own):
        with contextlib.suppress(FileNotFoundError):
            (d / name).unlink()
    for folder in (d / CLAIMS, d):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty


def column_names(directory) -> list[str]:
    """The columns of the table's parts, from their schemas (a part that cannot be read adds
    none: reading the table says so)."""
    names: dict = {}
    for p in parts(directory):
        try:
            names.update(dict.fromkeys(pq.read_schema(p).names))
        except _UNREADABLE:
            continue
    return list(names)


def done_keys(directory) -> set[str]:
    """Keys of the rows already in the table (reads the key column only); a damaged part
    is a ``DamagedTable``."""
    index = KeyIndex(directory)
    if index.damaged:
        raise DamagedTable(directory, index.damaged)
    return {f"{k:016x}" for k in index.keys}


def read_table(directory) -> pa.Table:
    """Every row of the table, one per key (the first written), sorted by point index. A
    damaged part is a ``DamagedTable`` (one line naming it and the fix)."""
    tables, damaged = [], {}
    for p in parts(directory):
        try:
            tables.append(_read_part(p))
        except FileNotFoundError:
            continue
        except _UNREADABLE as exc:
            damaged[p] = _damage(p, exc)
    if damaged:
        raise DamagedTable(directory, damaged)
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
    the two leaves duplicates that ``read_table`` drops). The caller holds the table's lock
    (``labbench.sweep.sharing``): another sweep may be merging too."""
    old = parts(directory)
    if len(old) < 2:
        return
    table = read_table(directory)
    with new_output(directory, f"part-{time.time_ns():x}-all-", ".parquet") as tmp:
        pq.write_table(table, tmp, **_CHECKSUMS)
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
