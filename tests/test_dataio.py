"""Loading records: CSV layout, every user error as one UserError line, sessions."""
import numpy as np
import pytest
from truthdata import chirp_recording, write_csv

from labbench.analysis.dataio import load_recording, position_quantum, recording_from_arrays
from labbench.errors import UserError


def _write(path, text):
    path.write_text(text)
    return path


def test_csv_roundtrip_any_column_order_and_metadata(tmp_path):
    rec = chirp_recording(n=2000)
    p = tmp_path / "r.csv"
    write_csv(rec, p, {"ve": "spring", "K": 50, "protocol": "chirp-id"})
    got = load_recording(p)
    assert np.array_equal(got.t, rec.t) and np.array_equal(got.force, rec.force)
    assert np.array_equal(got.position, rec.position)
    assert got.meta["ve"] == "spring" and got.meta["K"] == 50.0 and got.meta["fs"] == 1000.0
    assert got.fs == pytest.approx(1000.0)


def test_extra_columns_ignored(tmp_path):
    t = np.arange(100) / 1000
    rows = "\n".join(f"{a},{a * 2},{a * 3},9" for a in t)
    rec = load_recording(_write(tmp_path / "x.csv", "force,t,position,velocity\n" + rows + "\n"))
    assert np.allclose(rec.t, 2 * t) and np.allclose(rec.force, t)


@pytest.mark.parametrize("body, words", [
    ("t,force\n" + "".join(f"{k / 1000},{k}\n" for k in range(100)), "missing column(s) position"),
    ("t,force,position\n" + "".join(f"{k / 1000},1,0\n" for k in range(10)), "only 10 samples"),
    ("t,force,position\n" + "".join(f"{k / 1000},{'nan' if k == 50 else 1},0\n" for k in range(100)),
     "non-finite force at sample 50"),
    ("t,force,position\n" + "".join(f"{k / 1000},1,0\n" for k in range(100)).replace("0.07,", "0.0705,"),
     "not uniform at data row 71"),
    ("t,force,position\n1,2\n", "not a row of numbers"),
    ("# fs=1000\n", "no header row"),
])
def test_bad_csv_is_one_user_error(tmp_path, body, words):
    with pytest.raises(UserError) as exc:
        load_recording(_write(tmp_path / "bad.csv", body))
    msg = str(exc.value)
    assert words in msg and "\n" not in msg


def test_unreadable_and_missing_files(tmp_path):
    binary = tmp_path / "blob.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(UserError):
        load_recording(binary)
    with pytest.raises(UserError):
        load_recording(tmp_path / "nope.csv")
    with pytest.raises(UserError):
        load_recording(_write(tmp_path / "other.dat", "hello"))


def test_session_file_loads_through_the_same_entry_point(tmp_path):
    from session_recorder import synthetic_stream

    from labbench.sessions.session_format import SessionWriter

    writer = SessionWriter(tmp_path)
    for record in synthetic_stream(n_samples=3000):
        writer(record)
    writer.close()
    rec = load_recording(writer.path)
    assert len(rec) == 3000 and rec.meta["ve"] == "spring-damper" and rec.meta["K"] == 50.0
    assert rec.fs == pytest.approx(1000.0)


@pytest.mark.parametrize("hold", ["zoh", "sample"])
def test_session_records_how_the_force_reached_the_plant(tmp_path, hold):
    # the device says whether it holds a commanded force or measures one; the session
    # carries that into the analysis metadata (not a constant of the runner)
    import dataclasses

    from labbench.registry import make_protocol
    from labbench.rig import Rig
    from labbench.runner import run
    from labbench.sessions.session_format import SessionWriter
    from labbench.sim_backend.sim_device import SimDevice

    class Device(SimDevice):
        def describe(self):
            return dataclasses.replace(super().describe(), force_hold=hold)

    writer = SessionWriter(tmp_path)
    proto = make_protocol("chirp-id", f0_hz=2.0, f1_hz=10.0, duration_s=3.0, fade_s=0.5,
                          methods=("l2",))
    res = run(Device(Rig()), proto, [writer], rig=Rig())
    writer.close()
    assert res.status == "success", res.reason
    assert load_recording(writer.path).meta["force_hold"] == hold
    assert res.results["identification"]["l2"]["force_hold"] == {"value": hold, "source": "metadata"}


def test_arrays_validated_the_same_way():
    with pytest.raises(UserError):
        recording_from_arrays(np.arange(100), np.ones(99), np.ones(100))
    with pytest.raises(UserError):
        recording_from_arrays(np.arange(100)[::-1], np.ones(100), np.ones(100))


def test_position_quantum():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.standard_normal(20000)) * 1e-4
    assert position_quantum(x) is None
    assert position_quantum(np.round(x / 2.5e-5) * 2.5e-5) == pytest.approx(2.5e-5)
