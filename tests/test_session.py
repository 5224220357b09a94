"""Session files: exact round trip, torn and corrupt tails, listing, analysis arrays."""
import json
import os
import struct
import time

import numpy as np
import pytest
from session_recorder import VE, synthetic_stream

from labbench import records
from labbench.errors import RecordingError, UserError
from labbench.sessions.session_catalogue import list_sessions
from labbench.sessions.session_content import load_analysis_arrays
from labbench.sessions.session_format import MAGIC, SessionWriter, encode_record, looks_like_session, read_session


def _write(directory, stream, **kw):
    with SessionWriter(directory, **kw) as w:
        for rec in stream:
            w(rec)
    return w.path


def _assert_same(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key, value in a.items():
        if key == "data":
            assert value.keys() == b[key].keys()
            for name, arr in value.items():
                x, y = np.asarray(arr), b[key][name]
                assert x.dtype == y.dtype and x.shape == y.shape
                np.testing.assert_array_equal(x, y)
        else:
            assert json.loads(json.dumps(value)) == b[key], key


def test_round_trip_is_exact(tmp_path):
    stream = synthetic_stream(1050, page_size=100)
    path = _write(tmp_path, stream)
    assert path.parent == tmp_path and path.suffix == ".lbsession"
    assert "_etfe_" in path.name and stream[0]["uid"][:8] in path.name
    assert looks_like_session(path)
    reader = read_session(path)
    back = list(reader)
    assert reader.problem is None and reader.n_records == len(stream)
    assert [r["kind"] for r in back] == [r["kind"] for r in stream]
    for a, b in zip(stream, back):
        _assert_same(a, b)
    # arrays read back are writable, ordinary numpy arrays
    back[2]["data"]["position"][0] = 1.0


def test_special_values_and_dtypes_survive(tmp_path):
    data = {name: np.array([np.nan, np.inf, -0.0, 1e-300]) for name in records.CHANNELS}
    data["flags"] = np.array([0, 1, 2**40, -3], dtype=np.int64)
    data["seq"] = np.arange(4, dtype=np.uint32)
    stream = [records.start_record({"name": "r"}, {"name": "x", "w0": float("inf")}, None,
                                   extra=np.float32(2.5)),
              records.descriptor_record(0.001), records.page_record(0, data)]
    back = list(read_session(_write(tmp_path, stream)))
    assert back[0]["protocol"]["w0"] == float("inf") and back[0]["extra"] == 2.5
    for name, arr in data.items():
        assert back[2]["data"][name].dtype == arr.dtype
        np.testing.assert_array_equal(back[2]["data"][name], arr)


@pytest.mark.parametrize("chop", [1, 7, 24, 25, 500])
def test_torn_tail_reads_every_complete_record(tmp_path, chop):
    stream = synthetic_stream(1000)
    path = _write(tmp_path, stream)
    raw = path.read_bytes()
    last = len(encode_record(stream[-1], len(stream) - 1))
    path.write_bytes(raw[: len(raw) - last - chop])  # the stop record and a bit more are lost
    reader = read_session(path)
    back = list(reader)
    assert len(back) == len(stream) - 2
    assert "torn" in reader.problem
    for a, b in zip(stream, back):
        _assert_same(a, b)


def test_flipped_byte_stops_at_the_damaged_record(tmp_path):
    stream = synthetic_stream(1000)
    path = _write(tmp_path, stream)
    raw = bytearray(path.read_bytes())
    offset = len(MAGIC) + sum(len(encode_record(r, i)) for i, r in enumerate(stream[:5]))
    raw[offset + 100] ^= 0x40  # inside record 5's payload
    path.write_bytes(bytes(raw))
    reader = read_session(path)
    back = list(reader)
    assert len(back) == 5 and "checksum" in reader.problem
    for a, b in zip(stream, back):
        _assert_same(a, b)


def test_out_of_sequence_chunk_is_reported(tmp_path):
    stream = synthetic_stream(300)
    chunks = [encode_record(r, i) for i, r in enumerate(stream)]
    chunks[2] = encode_record(stream[2], 7)  # valid CRC, wrong sequence number
    path = tmp_path / "x.lbsession"
    path.write_bytes(MAGIC + b"".join(chunks))
    reader = read_session(path)
    assert len(list(reader)) == 2 and "sequence" in reader.problem


def test_lying_length_fields_do_not_allocate_or_crash(tmp_path):
    path = tmp_path / "x.lbsession"
    path.write_bytes(MAGIC + struct.pack("<4sIIQI", b"REC:", 2**20, 2**32 - 1, 0, 0) + b"{}")
    reader = read_session(path)
    assert list(reader) == [] and "torn" in reader.problem
    path.write_bytes(MAGIC + struct.pack("<4sIIQI", b"REC:", 2**31, 0, 0, 0) + b"{}")
    reader = read_session(path)
    assert list(reader) == [] and "corrupt" in reader.problem


def test_bad_files_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="not found"):
        read_session(tmp_path / "missing.lbsession")
    (tmp_path / "a.csv").write_text("t,force,position\n")
    with pytest.raises(UserError, match="not a labbench session"):
        read_session(tmp_path / "a.csv")
    assert not looks_like_session(tmp_path / "a.csv")
    with pytest.raises(UserError, match="directory"):
        read_session(tmp_path)
    (tmp_path / "file").write_text("")
    with pytest.raises(UserError, match="is a file"):
        SessionWriter(tmp_path / "file")


def test_writer_contract(tmp_path):
    w = SessionWriter(tmp_path / "new" / "dir", name="mine")
    assert w.path is None
    with pytest.raises(ValueError, match="start record"):
        w(records.descriptor_record(0.001))
    stream = synthetic_stream(200, status=None)
    for rec in stream:
        w(rec)
    assert w.path == tmp_path / "new" / "dir" / "mine.lbsession"
    # written through to the kernel at once: readable before close
    assert len(list(read_session(w.path))) == len(stream)
    w.close()
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w(stream[-1])
    with pytest.raises(RecordingError, match="nothing recorded: cannot create session file .*mine"):
        _write(tmp_path / "new" / "dir", stream, name="mine")


def test_list_sessions_reports_status_and_samples(tmp_path):
    done = _write(tmp_path, synthetic_stream(1234, protocol="chirp-id"))
    open_run = _write(tmp_path, synthetic_stream(500, status=None))
    (tmp_path / "notes.txt").write_text("hello")
    found = {s.path: s for s in list_sessions(tmp_path)}
    assert set(found) == {done, open_run}
    assert found[done].status == "success" and found[done].n_samples == 1234
    assert found[done].protocol == "chirp-id" and found[done].rig_name == "synthetic test rig"
    assert found[open_run].status == "incomplete" and found[open_run].n_samples == 500
    assert len(found[done].uid) == 32 and found[done].time > 0
    with pytest.raises(UserError):
        list_sessions(tmp_path / "nope")


def test_load_analysis_arrays(tmp_path):
    stream = synthetic_stream(1000)
    out = load_analysis_arrays(_write(tmp_path, stream))
    joined = records.concat_pages(stream)
    np.testing.assert_array_equal(out["force"], joined["excitation"])
    np.testing.assert_array_equal(out["position"], joined["position"])
    np.testing.assert_array_equal(out["t"], joined["t"])
    meta = out["meta"]
    assert meta["fs"] == pytest.approx(1000.0) and meta["protocol"] == "etfe"
    assert (meta["ve"], meta["K"], meta["B"], meta["w0"], meta["td"]) == (
        VE.kind, VE.K, VE.B, VE.w0, VE.td)


def test_meta_from_a_protocol_config(tmp_path):
    stream = synthetic_stream(100)
    stream[0]["protocol"] = {"protocol": "etfe", "ve": "damper", "K": 50.0, "B": 2.0,
                             "w0_rad_s": None, "td_s": 0.002, "sample_time_s": 0.001}
    meta = load_analysis_arrays(_write(tmp_path, stream))["meta"]
    assert meta["protocol"] == "etfe" and meta["ve"] == "damper"
    assert (meta["K"], meta["B"], meta["td"]) == (0.0, 2.0, 0.002) and "w0" not in meta


def test_session_without_samples_is_a_user_error(tmp_path):
    path = _write(tmp_path, synthetic_stream(0))
    with pytest.raises(UserError, match="no samples"):
        load_analysis_arrays(path)


def test_writer_fsyncs_while_idle(tmp_path, monkeypatch):
    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd)))
    w = SessionWriter(tmp_path, fsync_interval_s=0.05)
    w(synthetic_stream(0)[0])
    deadline = time.monotonic() + 2.0
    while not calls and time.monotonic() < deadline:
        time.sleep(0.01)
    assert calls, "no fsync within 2 s of a write"
    w.close()


def test_replay_feeds_the_same_stream(tmp_path):
    from labbench.sessions.replay import StreamSummary, replay

    stream = synthetic_stream(1000)
    path = _write(tmp_path, stream)
    got, summary = [], StreamSummary()
    reader = replay(path, [got.append, summary])
    assert reader.problem is None and len(got) == len(stream)
    for a, b in zip(stream, got):
        _assert_same(a, b)
    s = summary.as_dict()
    assert (s["samples"], s["pages"], s["dropped_samples"], s["status"]) == (1000, 10, 0, "success")
    assert s["duration_s"] == pytest.approx(0.999)
    assert [e["name"] for e in s["events"]] == ["force_limit"]
    joined = records.concat_pages(stream)
    assert s["max_abs_command_n"] == np.max(np.abs(joined["command"]))


def test_summary_counts_dropped_samples():
    from labbench.sessions.replay import StreamSummary

    stream = synthetic_stream(300)
    for page in stream[3:5]:  # 7 samples missing inside page 1
        page["data"]["seq"] = page["data"]["seq"] + 7
    stream[3]["data"]["seq"][:50] -= 7
    s = StreamSummary()
    records.fan_out(stream, [s])
    assert s.dropped == 7


def test_replay_paces_by_sample_time(tmp_path):
    from labbench.sessions.replay import replay

    path = _write(tmp_path, synthetic_stream(1000, events=False))
    now = [0.0]
    due = []

    def sleep(dt):
        now[0] += dt

    def note(rec):
        if rec["kind"] == records.PAGE:
            due.append((now[0], float(rec["data"]["t"][-1])))

    replay(path, [note], speed=2.0, clock=lambda: now[0], sleep=sleep)
    t_first = due[0][1]
    for wall, t in due:
        assert wall == pytest.approx((t - t_first) / 2.0)
    assert due[-1][0] == pytest.approx((0.999 - 0.099) / 2.0)


def test_replay_stops_on_request(tmp_path):
    import threading

    from labbench.sessions.replay import replay

    path = _write(tmp_path, synthetic_stream(1000))
    stop = threading.Event()
    got = []

    def consumer(rec):
        got.append(rec)
        if rec["kind"] == records.PAGE and rec["index"] == 2:
            stop.set()

    replay(path, [consumer], speed=1.0, stop=stop)
    assert [r["kind"] for r in got].count(records.PAGE) == 3


def test_replay_cli(tmp_path, capsys):
    from labbench.cli import main

    path = _write(tmp_path, synthetic_stream(500, status=None))
    assert main(["replay", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples"] == 500 and out["status"] == "incomplete"
    assert out["damaged_tail"] is None
    raw = path.read_bytes()
    path.write_bytes(raw[:-10])
    t0 = time.monotonic()
    assert main(["replay", str(path), "--speed", "1"]) == 0
    assert time.monotonic() - t0 >= 0.3  # ~0.4 s of samples survive, paced in real time
    cap = capsys.readouterr()
    assert "samples   400" in cap.out and "torn" in cap.err
    assert main(["replay", str(tmp_path / "nope")]) == 2
    assert main(["replay", str(path), "--speed", "0"]) == 2
