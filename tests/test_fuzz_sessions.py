"""Fuzz: session files whose checksums are valid but whose content is hostile.

Each corruption below turns a good session into one a buggy or hostile writer
could produce (wrong-typed header fields, nested JSON, 2-D or mismatched pages,
missing channels, shapes of 2^70, huge or non-finite time stamps, floods of
events, unknown kinds); every entry point that reads sessions (replay, paced
replay, analyze id/etfe, export CSV/HDF5, report) must give a result or one
error line (tests/fuzzing.py). The report, the slowest entry point, sees every
corruption under ``-m slow`` and a fixed sample otherwise.

Then the fields: every field of the non-page records of two real sessions
(chirp-ID, ETFE), down to six levels, given each JSON type it does not have,
and every key of every record (the first page's included) removed; the report's
content must come out of each (a field of the wrong shape, or an object without
a key it needs, is left out and flagged, ``labbench.report.shapes``), and every
other reader (replay, analyze id/etfe, export CSV/HDF5, ``labbench.load``) must
give a result or one error line. A sample by default, all of them under ``-m slow``.
"""
from __future__ import annotations

import copy

import numpy as np
import pytest
from fuzzing import Tally, items_of, run_cli, run_cli_isolated, write_chunks
from fuzzing import scratch_cwd  # noqa: F401 - autouse fixture
from session_recorder import synthetic_stream

START, DESC, PAGE0, STOP = 0, 1, 2, -1


def _set(i, key, value):
    def f(items):
        items[i][0][key] = value
        return items
    return f


def _array(field, value, channel=0, page=PAGE0):
    def f(items):
        items[page][0]["arrays"][channel][field] = value
        return items
    return f


def _nest(depth):
    def f(items):
        items[START][0]["protocol"]["deep"] = json_nest(depth)
        return items
    return f


def json_nest(depth):
    v = 0
    for _ in range(depth):
        v = [v]
    return v


def _raw_json(i, body: bytes):
    def f(items):
        items[i][0] = body
        return items
    return f


def _drop_channel(items):
    head, data = items[PAGE0]
    spec = head["arrays"].pop()
    n = spec["shape"][0] * np.dtype(spec["dtype"]).itemsize
    items[PAGE0][1] = data[:-n]
    return items


def _mismatched_lengths(items):
    head, data = items[PAGE0]
    spec = head["arrays"][-1]
    itemsize = np.dtype(spec["dtype"]).itemsize
    spec["shape"] = [spec["shape"][0] - 1]
    items[PAGE0][1] = data[:-itemsize]
    return items


def _times(values):
    """Overwrite the t channel of the first page (same bytes length)."""
    def f(items):
        head, data = items[PAGE0]
        n = head["arrays"][0]["shape"][0]
        assert head["arrays"][0]["name"] == "t"
        t = np.resize(np.asarray(values, "<f8"), n)
        items[PAGE0][1] = t.tobytes() + data[8 * n:]
        return items
    return f


def _flood(n):
    def f(items):
        ev = {"kind": "event", "t": 0.5, "name": "force_limit", "reason": "x" * 40}
        return items[:3] + [[dict(ev, t=0.001 * k), b""] for k in range(n)] + items[3:]
    return f


def _swap_kind(i, kind):
    return _set(i, "kind", kind)


def _data_on(i):
    def f(items):
        items[i][1] = b"\x00" * 16
        return items
    return f


def _only(*indices):
    def f(items):
        return [items[i] for i in indices]
    return f


CORRUPTIONS = {
    "start uid number": _set(START, "uid", 5),
    "start time text": _set(START, "time", "yesterday"),
    "start time 1e308": _set(START, "time", 1e308),
    "start time negative": _set(START, "time", -1e20),
    "start rig list": _set(START, "rig", [1, 2]),
    "start rig text": _set(START, "rig", "rig"),
    "start protocol number": _set(START, "protocol", 7),
    "start protocol ve bogus": lambda it: (it[START][0]["protocol"].update(ve={"kind": 5}), it)[1],
    "start protocol K 1e308": lambda it: (it[START][0]["protocol"]["ve"].update(K=1e308), it)[1],
    "start seed negative": _set(START, "seed", -1),
    "start seed float": _set(START, "seed", 1.5),
    "start nested 40": _nest(40),
    "start nested 100000": _raw_json(START, b'{"kind":"start","x":' + b"[" * 100000 + b"]" * 100000 + b"}"),
    "start not an object": _raw_json(START, b"[1, 2, 3]"),
    "start invalid utf8": _raw_json(START, b'{"kind":"start","uid":"\xff\xfe"}'),
    "start NaN time": _raw_json(START, b'{"kind":"start","time":NaN}'),
    "descriptor T zero": _set(DESC, "sample_time_s", 0),
    "descriptor T 1e-320": _set(DESC, "sample_time_s", 1e-320),
    "descriptor T 1e308": _set(DESC, "sample_time_s", 1e308),
    "descriptor T text": _set(DESC, "sample_time_s", "fast"),
    "descriptor channels list": _set(DESC, "channels", ["t"]),
    "page 2-D": _array("shape", [50, 2]),
    "page shape 2^70": _array("shape", [2**70]),
    "page shape negative": _array("shape", [-1]),
    "page shape text": _array("shape", "100"),
    "page dtype unicode": _array("dtype", "<U8"),
    "page dtype object": _array("dtype", "|O"),
    "page dtype void": _array("dtype", "|V8"),
    "page dtype bogus": _array("dtype", "float99"),
    "page dtype big-endian": _array("dtype", ">f8"),
    "page name number": _array("name", 3),
    "page arrays missing": lambda it: (it[PAGE0][0].pop("arrays"), it)[1],
    "page lacks a channel": _drop_channel,
    "page lengths differ": _mismatched_lengths,
    "page index text": _set(PAGE0, "index", "zero"),
    "page t huge": _times([1e300, 2e300]),
    "page t NaN": _times([np.nan]),
    "page t decreasing": _times(np.arange(100.0, 0.0, -0.001)),
    "event t 1e300": lambda it: it[:3] + [[{"kind": "event", "t": 1e300, "name": "x", "reason": ""}, b""]] + it[3:],
    "event name dict": lambda it: it[:3] + [[{"kind": "event", "t": 0.1, "name": {}, "reason": 5}, b""]] + it[3:],
    "events 20000": _flood(20_000),
    "stop status number": _set(STOP, "status", 3),
    "stop results list": _set(STOP, "results", [1]),
    "stop results m 1e308": _set(STOP, "results", {"m": 1e308, "b": -1e308}),
    "stop timing text": _set(STOP, "timing", "fast"),
    "stop n_samples 2^70": _set(STOP, "n_samples", 2**70),
    "stop status exploded": _set(STOP, "status", "exploded"),
    "stop cause bogus": lambda it: (it[STOP][0].update(status="failed", cause="bogus"), it)[1],
    "start rig T text": lambda it: (it[START][0]["rig"].update(sample_time_s="abc"), it)[1],
    "start rig T negative": lambda it: (it[START][0]["rig"].update(sample_time_s=-1), it)[1],
    "start rig force limit 1e308": lambda it: (it[START][0]["rig"].update(force_limit_n=1e308),
                                               it)[1],
    "start rig lever arm 1e-300": lambda it: (it[START][0]["rig"].update(lever_arm_m=1e-300),
                                              it)[1],
    "start safety force limit 1e308": _set(START, "safety", {"force_limit_n": 1e308}),
    "start device force limit inf": _raw_json(START, b'{"kind":"start","device":{"force_limit_n":'
                                                     b'Infinity}}'),
    "unknown kind": _swap_kind(PAGE0, "bogus"),
    "kind missing": lambda it: (it[DESC][0].pop("kind"), it)[1],
    "data on an event": _data_on(DESC),
    "no pages": _only(START, DESC, STOP),
    "start only": _only(START),
    "pages without start": lambda it: it[1:],
}

READERS = {
    "replay": lambda p, d: ["replay", p],
    "replay --speed 1000": lambda p, d: ["replay", p, "--speed", "1000"],
    "analyze id": lambda p, d: ["analyze", "id", p],
    "analyze etfe": lambda p, d: ["analyze", "etfe", p],
    "export --csv": lambda p, d: ["export", p, "--csv", d / "out.csv"],
    "export --hdf5": lambda p, d: ["export", p, "--hdf5", d / "out.h5"],
}
REPORT_SAMPLE = ("start protocol K 1e308", "events 20000", "stop results m 1e308")


@pytest.fixture(scope="module")
def good_items():
    return items_of(synthetic_stream(3000, page_size=500, status="success"))


def _session(tmp_path, name, good_items):
    items = CORRUPTIONS[name](copy.deepcopy(good_items))
    path = tmp_path / (name.replace(" ", "_").replace("/", "") + ".lbsession")
    return write_chunks(path, items)


def _fuzz(tmp_path, good_items, names, readers):
    tally = Tally()
    for name in names:
        path = _session(tmp_path, name, good_items)
        for entry, argv in readers.items():
            out = tmp_path / "out"
            out.mkdir(exist_ok=True)
            tally.add(entry, run_cli(argv(path, out)))
            for f in out.iterdir():
                if f.is_file():
                    f.unlink()
    print("\n" + tally.report())
    assert tally.failures == []


def test_hostile_sessions_every_reader(tmp_path, good_items):
    _fuzz(tmp_path, good_items, CORRUPTIONS, READERS)


def test_hostile_sessions_report_sample(tmp_path, good_items):
    _fuzz(tmp_path, good_items, REPORT_SAMPLE,
          {"report": lambda p, d: ["report", p, "-o", d / "r", "--force"]})


@pytest.mark.slow
def test_hostile_sessions_report_all(tmp_path, good_items):
    _fuzz(tmp_path, good_items, CORRUPTIONS,
          {"report": lambda p, d: ["report", p, "-o", d / "r", "--force"]})


@pytest.mark.slow
def test_a_flood_of_300000_events(tmp_path, good_items):
    """The issue's case: a report (and a replay, an export) of a session with 300 000 events,
    each in a child process under RLIMIT_AS (tracemalloc would slow the parsing tenfold)."""
    items = _flood(300_000)(copy.deepcopy(good_items))
    path = write_chunks(tmp_path / "flood.lbsession", items)
    tally = Tally()
    for entry, argv in {"replay": ["replay", path],
                        "report": ["report", path, "-o", tmp_path / "r"],
                        "export --csv": ["export", path, "--csv", tmp_path / "f.csv"]}.items():
        tally.add(entry, run_cli_isolated(argv, tmp_path))
    print("\n" + tally.report())
    assert tally.failures == []
    assert (tmp_path / "r" / "flood.pdf").stat().st_size > 0


# Values a session's checksums allow but labbench never writes (issue 44: each was read by
# every reader without a word): the reader stops there, as at a damaged record, and names it.
NOT_AS_WRITTEN = {"stop status exploded": "status 'exploded' is none of success, aborted, failed",
                  "stop cause bogus": "cause 'bogus' is none of",
                  "start rig T text": "[rig] sample_time_s must be a number in",
                  "start rig T negative": "[rig] sample_time_s must be a number in",
                  "start rig force limit 1e308": "[rig] force_limit_n must be a number in",
                  "start rig lever arm 1e-300": "[rig] lever_arm_m must be a number in",
                  "start safety force limit 1e308": "force_limit_n",
                  "start device force limit inf": "device force_limit_n = inf is not a number"}


def test_a_session_not_as_labbench_writes_it_is_named_in_one_line_by_every_reader(
        tmp_path, good_items):
    for name, words in NOT_AS_WRITTEN.items():
        path = _session(tmp_path, name, good_items)
        for k, (entry, argv) in enumerate({**READERS, "report": lambda p, d: [
                "report", p, "-o", d / "r", "--force"]}.items()):
            out = tmp_path / f"{path.stem}-{k}"
            out.mkdir()
            o = run_cli(argv(path, out))
            assert o.crash is None and o.code in (0, 2), (name, entry, o.err, o.crash)
            said = [x for x in o.err.splitlines() if str(path) in x and words in x]
            assert len(said) == 1, (name, entry, o.err)
            assert "stream ends early" in said[0] or ": error: " in said[0], said


def test_the_good_session_gives_results(tmp_path, good_items):
    """The base of the corruptions is itself accepted everywhere (the fuzzing starts from a
    session every reader takes)."""
    path = write_chunks(tmp_path / "good.lbsession", good_items)
    for entry, argv in READERS.items():
        o = run_cli(argv(path, tmp_path))
        assert o.code == 0 and o.crash is None, (entry, o.err, o.crash)


# ----- field types mutated: real sessions, each field given every other JSON type -----------
JSON_TYPES = {"text": "x", "number": 7, "list": [1], "object": {"x": 1}, "null": None,
              "bool": True}


def _json_type(value) -> str:
    if isinstance(value, bool):
        return "bool"
    return {str: "text", int: "number", float: "number", list: "list", dict: "object",
            type(None): "null"}[type(value)]


def _fields(value, path=(), depth=6):
    """(path, value) of every field down to ``depth`` (a list: its first element)."""
    if isinstance(value, dict):
        members = list(value.items())
    elif isinstance(value, list) and value:
        members = [(0, value[0])]
    else:
        return
    for key, item in members:
        yield path + (key,), item
        if depth > 1:
            yield from _fields(item, path + (key,), depth - 1)


def type_mutations(items):
    """(name, items) for every field of every record but the pages (whose typed header the
    value corpus above covers) given each JSON type it does not have."""
    for i, (head, _) in enumerate(items):
        if head.get("kind") == "page":
            continue
        for path, value in _fields(head):
            if path == ("kind",):
                continue
            for type_name, other in JSON_TYPES.items():
                if type_name == _json_type(value):
                    continue
                mutated = copy.deepcopy(items)
                target = mutated[i][0]
                for key in path[:-1]:
                    target = target[key]
                target[path[-1]] = other
                yield f"{head['kind']}[{i}] {'.'.join(map(str, path))} -> {type_name}", mutated


def key_removals(items):
    """(name, items) with one key of one record removed, for every key of every record down
    to six levels (a list: its first element); of the pages, the first one's."""
    for i, (head, _) in enumerate(items):
        if head.get("kind") == "page" and i != next(
                k for k, (h, _) in enumerate(items) if h.get("kind") == "page"):
            continue
        for path, _value in _fields(head):
            if path == ("kind",) or isinstance(path[-1], int):
                continue
            mutated = copy.deepcopy(items)
            target = mutated[i][0]
            for key in path[:-1]:
                target = target[key]
            del target[path[-1]]
            yield f"{head['kind']}[{i}] without {'.'.join(map(str, path))}", mutated


@pytest.fixture(scope="module")
def real_items(tmp_path_factory):
    """A chirp-ID and an ETFE session of the simulator: the records every analysis writes."""
    from labbench.report import session as report_session
    from labbench.sessions.session_format import read_session

    out = tmp_path_factory.mktemp("real")
    for argv in (["run", "chirp-id", "--duration-s", "4", "--f0-hz", "0.5"],
                 ["run", "etfe", "--duration-s", "2", "--seed", "1"]):
        o = run_cli([*argv, "--device", "sim", "--out", out], time_limit_s=120)
        assert o.code == 0 and o.crash is None, o.err
    paths = sorted(out.glob("*.lbsession"))
    assert [report_session.load(p).malformed for p in paths] == [(), ()]  # nothing false
    return [items_of(list(read_session(p))) for p in paths]


def _report_content(tmp_path, real_items, every: int,
                    mutations=type_mutations) -> tuple[int, list[str]]:
    """Build the report of every ``every``-th mutated session in this process (the
    content, where a record's fields are read; the rendering takes only what it built)."""
    from labbench.errors import LabbenchError
    from labbench.report.content import build

    n, failures = 0, []
    for items in real_items:
        for k, (name, mutated) in enumerate(mutations(items)):
            if k % every:
                continue
            path = write_chunks(tmp_path / "case.lbsession", mutated)
            n += 1
            try:
                build([path])
            except LabbenchError:
                pass  # one error line from the CLI
            except Exception as exc:  # noqa: BLE001 - what the fuzzing looks for
                failures.append(f"{name}: {type(exc).__name__}: {exc}")
    return n, failures


def test_report_content_of_type_mutated_sessions_sample(tmp_path, real_items):
    """Every 13th case (all six types and every record kind appear); -m slow: all of them."""
    n, failures = _report_content(tmp_path, real_items, every=13)
    print(f"\nreport content: {n} type-mutated sessions")
    assert n > 180 and failures == []


@pytest.mark.slow
def test_report_content_of_type_mutated_sessions_all(tmp_path, real_items):
    n, failures = _report_content(tmp_path, real_items, every=1)
    print(f"\nreport content: {n} type-mutated sessions")
    assert n > 2500 and failures == []


def test_report_content_of_sessions_missing_keys_sample(tmp_path, real_items):
    """Every 7th removed key (every record kind appears); -m slow: all of them."""
    n, failures = _report_content(tmp_path, real_items, every=7, mutations=key_removals)
    print(f"\nreport content: {n} sessions missing a key")
    assert n > 60 and failures == []


@pytest.mark.slow
def test_report_content_of_sessions_missing_keys_all(tmp_path, real_items):
    n, failures = _report_content(tmp_path, real_items, every=1, mutations=key_removals)
    print(f"\nreport content: {n} sessions missing a key")
    assert n > 450 and failures == []


def _load_api(path) -> str | None:
    """``labbench.load`` and what it offers without an analysis: a LabbenchError is its one
    clear error; anything else escaping is what the fuzzing looks for."""
    import labbench
    from labbench.errors import LabbenchError

    try:
        session = labbench.load(path)
        repr(session)
        session.to_dataframe()
    except LabbenchError:
        pass
    except Exception as exc:  # noqa: BLE001
        return f"{type(exc).__name__}: {exc}"
    return None


def _every_reader(tmp_path, real_items, mutations, every: int) -> tuple[int, Tally, list]:
    """Every ``every``-th mutated session through the CLI's readers and ``labbench.load``."""
    tally, loads, n = Tally(), [], 0
    out = tmp_path / "out"
    out.mkdir()
    for items in real_items:
        for k, (name, mutated) in enumerate(mutations(items)):
            if k % every:
                continue
            n += 1
            path = write_chunks(tmp_path / "case.lbsession", mutated)
            for entry, argv in READERS.items():
                if entry == "replay --speed 1000":
                    continue  # paced: the same reading as replay, seconds per case
                tally.add(entry, run_cli(argv(path, out)))
                for f in out.iterdir():
                    f.unlink()
            if (problem := _load_api(path)) is not None:
                loads.append(f"{name}: {problem}")
    print(f"\n{n} sessions\n" + tally.report())
    return n, tally, loads


def test_every_reader_of_sessions_missing_keys_sample(tmp_path, real_items):
    n, tally, loads = _every_reader(tmp_path, real_items, key_removals, every=17)
    assert n > 25 and tally.failures == [] and loads == []


def test_every_reader_of_type_mutated_sessions_sample(tmp_path, real_items):
    n, tally, loads = _every_reader(tmp_path, real_items, type_mutations, every=97)
    assert n > 25 and tally.failures == [] and loads == []


@pytest.mark.parametrize("record, path, value", [
    *[("start", ("protocol", key), value) for key in ("K", "B", "w0_rad_s", "td_s",
                                                       "sample_time_s")
      for value in ("x", [1], {"x": 1})],
    ("descriptor", ("channels", "position"), {"x": 1}),
    ("descriptor", ("channels", "command"), None),
])
def test_what_the_type_fuzz_found(tmp_path, real_items, record, path, value):
    """Tracebacks the full corpus found in analyze, export and labbench.load: a start record
    whose protocol numbers are not numbers (float() of a list), a descriptor whose channel
    unit is not text (HDF5 has no type for it)."""
    items = copy.deepcopy(real_items[1])
    (head,) = [h for h, _ in items if h.get("kind") == record]
    head[path[0]][path[1]] = value
    session = write_chunks(tmp_path / "case.lbsession", items)
    tally = Tally()
    for entry, argv in READERS.items():
        if entry != "replay --speed 1000":
            tally.add(entry, run_cli(argv(session, tmp_path)))
    assert tally.failures == [] and _load_api(session) is None


@pytest.mark.slow
def test_every_reader_of_sessions_missing_keys_all(tmp_path, real_items):
    n, tally, loads = _every_reader(tmp_path, real_items, key_removals, every=1)
    assert n > 450 and tally.failures == [] and loads == []


@pytest.mark.slow
def test_every_reader_of_type_mutated_sessions_all(tmp_path, real_items):
    n, tally, loads = _every_reader(tmp_path, real_items, type_mutations, every=1)
    assert n > 2500 and tally.failures == [] and loads == []


def test_report_of_a_precheck_without_its_ve(tmp_path, real_items):
    """The issue's traceback (KeyError 've' in the pre-check table): the report is written,
    the check is left out and page 1 names it; a VE dict the VE cannot take is left out of the
    table with a note."""
    for change, named in ((lambda c: c.pop("ve"), "element(s) not an object with ve"),
                          (lambda c: c["ve"].update(x=1), "left out: not a valid VE")):
        items = copy.deepcopy(real_items[1])  # the ETFE
        (head,) = [h for h, _ in items if h.get("kind") == "start"]
        change(head["precheck"]["checks"][0])
        session = write_chunks(tmp_path / "case.lbsession", items)
        o = run_cli(["report", session, "-o", tmp_path / "r", "--force"], time_limit_s=120)
        assert o.code == 0 and o.crash is None, (o.err, o.crash)
        (html,) = (tmp_path / "r").glob("*.html")
        assert named in html.read_text(encoding="utf-8")


@pytest.mark.parametrize("kind, path, value, named", [
    ("start", ("precheck",), "checks", "start.precheck: str where an object is due"),
    ("stop", ("results", "identification"), "l2", "stop.results.identification: str where"),
    ("stop", ("timing", "histogram", "counts"), "many", "stop.timing.histogram.counts: str"),
])
def test_report_of_the_issue_cases_is_written_and_flags_the_field(tmp_path, real_items, kind,
                                                                  path, value, named):
    """The whole command (HTML and PDF): a result, and page 1 names the field left out."""
    items = copy.deepcopy(real_items[0])  # the chirp-ID
    (head,) = [h for h, _ in items if h.get("kind") == kind]
    for key in path[:-1]:
        head = head[key]
    head[path[-1]] = value
    session = write_chunks(tmp_path / "case.lbsession", items)
    o = run_cli(["report", session, "-o", tmp_path / "r"], time_limit_s=120)
    assert o.code == 0 and o.crash is None, (o.err, o.crash)
    (html,) = (tmp_path / "r").glob("*.html")
    assert named in html.read_text(encoding="utf-8")
