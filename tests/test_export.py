"""Export: HDF5 read back with h5py, CSV read back with numpy (and the analysis loader when present)."""
import json

import h5py
import numpy as np
import pytest
from session_recorder import VE, synthetic_stream

from labbench import records
from labbench.cli import main
from labbench.analysis import dataio
from labbench.sessions.export import CSV_COLUMNS
from labbench.sessions.session_format import SessionWriter


@pytest.fixture
def session(tmp_path):
    stream = synthetic_stream(1500, status="success")
    with SessionWriter(tmp_path / "s") as w:
        for rec in stream:
            w(rec)
    return w.path, stream


def test_hdf5_round_trip(tmp_path, session, capsys):
    path, stream = session
    out = tmp_path / "run.h5"
    assert main(["export", str(path), "--hdf5", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    joined = records.concat_pages(stream)
    with h5py.File(out, "r") as f:
        assert f.attrs["uid"] == stream[0]["uid"] and f.attrs["status"] == "success"
        assert f.attrs["protocol"] == "etfe" and f.attrs["sample_time_s"] == VE.T
        for name, unit in records.CHANNELS.items():
            ds = f["channels"][name]
            assert ds.attrs["units"] == unit and ds.dtype == joined[name].dtype
            np.testing.assert_array_equal(ds[()], joined[name])
        np.testing.assert_array_equal(f["channels/force"][()], joined["excitation"])
        start = json.loads(f["records/start"][()])
        assert start["protocol"]["ve"]["K"] == VE.K and start["rig"] == stream[0]["rig"]
        events = json.loads(f["records/events"][()])
        assert [e["name"] for e in events] == ["force_limit"]
        assert json.loads(f["records/stop"][()])["timing"]["overruns"] == 0


def test_csv_round_trip(tmp_path, session):
    path, stream = session
    out = tmp_path / "run.csv"
    assert main(["export", str(path), "--csv", str(out)]) == 0
    lines = out.read_text().splitlines()
    meta = dict(line[2:].split("=", 1) for line in lines if line.startswith("# "))
    assert meta["protocol"] == "etfe" and float(meta["fs"]) == 1000.0
    assert meta["ve"] == "spring-damper" and float(meta["K"]) == VE.K
    assert float(meta["w0"]) == VE.w0 and float(meta["td"]) == VE.td
    header = next(line for line in lines if not line.startswith("#"))
    assert tuple(header.split(",")) == CSV_COLUMNS
    table = np.loadtxt(out, delimiter=",", comments="#", skiprows=len(meta) + 1)
    joined = records.concat_pages(stream)
    for i, name in enumerate(CSV_COLUMNS):
        want = joined["excitation" if name == "force" else name]
        np.testing.assert_array_equal(table[:, i], want)  # exact: 17 significant digits


def test_csv_reads_with_the_analysis_loader(tmp_path, session):
    path, stream = session
    out = tmp_path / "run.csv"
    main(["export", str(path), "--csv", str(out)])
    joined = records.concat_pages(stream)
    for source in (out, path):  # the CSV and the session itself
        rec = dataio.load_recording(source)
        np.testing.assert_array_equal(rec.force, joined["excitation"])
        np.testing.assert_array_equal(rec.position, joined["position"])
        np.testing.assert_allclose(rec.t, joined["t"], rtol=0, atol=1e-12)


def test_export_errors_are_one_line(tmp_path, session, capsys):
    path, _ = session
    assert main(["export", str(tmp_path / "none.lbsession"), "--csv", str(tmp_path / "x.csv")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["export", str(path), "--csv", str(tmp_path / "no" / "x.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["export", str(path), "--hdf5", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "directory" in err and len(err.strip().splitlines()) == 1


def test_hdf5_time_is_the_axis_of_every_channel(tmp_path, session):
    """Time is the dimension scale of each channel; units, descriptions, compression and an
    ISO 8601 start time are attributes a reader sees without knowing labbench."""
    from datetime import datetime

    path, stream = session
    out = tmp_path / "run.h5"
    assert main(["export", str(path), "--hdf5", str(out)]) == 0
    joined = records.concat_pages(stream)
    with h5py.File(out, "r") as f:
        t = f["channels/t"]
        assert t.is_scale and t.attrs["NAME"] == b"time"
        for name in records.CHANNELS:
            ds = f["channels"][name]
            assert ds.compression == "gzip" and ds.shuffle
            assert ds.attrs["description"] == records.DESCRIPTIONS[name]
            if name != "t":
                assert ds.dims[0].label == "time" and len(ds.dims[0]) == 1
                np.testing.assert_array_equal(ds.dims[0][0][()], joined["t"])
        started = datetime.fromisoformat(f.attrs["start_time"])
        assert started.utcoffset() is not None
        assert started.timestamp() == pytest.approx(stream[0]["time"], abs=1.0)
        assert "time" not in f.attrs  # no bare epoch float
    # gzip + shuffle: smaller than the raw arrays (the synthetic data are smooth)
    raw = sum(np.asarray(v).nbytes for v in joined.values())
    assert out.stat().st_size < raw


def test_frequency_response_csv(tmp_path, session, capsys):
    import labbench

    path, _ = session
    out = tmp_path / "fr.csv"
    assert main(["analyze", "etfe", str(path), "--csv", str(out), "--m", "0.094", "--b", "0.1"]) == 0
    capsys.readouterr()
    lines = out.read_text().splitlines()
    meta = dict(line[2:].split("=", 1) for line in lines if line.startswith("# "))
    header = lines[len(meta)].split(",")
    assert header[:2] == ["w_rad_s", "f_hz"] and "Z_theory_re" in header
    table = np.loadtxt(out, delimiter=",", skiprows=len(meta) + 1)
    fr = labbench.load(path).etfe(m=0.094, b=0.1)
    col = {name: table[:, i] for i, name in enumerate(header)}
    np.testing.assert_array_equal(col["w_rad_s"], fr.w)
    np.testing.assert_allclose(col["f_hz"], fr.w / (2 * np.pi), rtol=1e-15)
    np.testing.assert_array_equal(col["ES"], fr.ES)
    np.testing.assert_array_equal(col["Z_theory_im"], fr.Z_theory.imag)
    wb = meta["wb_star_rad_s"]  # none on this 1.5 s record: too short for a rendered damping
    assert meta["theory_model"] == "sampled" and (None if wb == "None" else float(wb)) == fr.wb_star
    assert main(["analyze", "etfe", str(path), "--csv", str(out)]) == 2  # exists: --force
    assert "--force" in capsys.readouterr().err
    assert fr.to_csv(out, force=True) == out


def test_display_units_change_only_what_is_printed(tmp_path, session, capsys):
    from labbench.errors import UserError
    from labbench.readout.units import DisplayUnits

    u = DisplayUnits.parse("mm,Hz,deg")
    assert (u.length_of(0.0123), u.frequency_of(2 * np.pi), u.angle_of(np.pi)) == \
        pytest.approx((12.3, 1.0, 180.0))
    with pytest.raises(UserError, match="two frequency units"):
        DisplayUnits.parse("Hz,rad/s")
    with pytest.raises(UserError, match="unknown display unit"):
        DisplayUnits.parse("furlong")
    path, _ = session
    assert main(["analyze", "etfe", str(path)]) == 0
    si = capsys.readouterr().out
    assert main(["--units", "Hz", "analyze", "etfe", str(path)]) == 0
    hz = capsys.readouterr().out
    rad_row = si.splitlines()[si.splitlines().index(next(x for x in si.splitlines() if "w rad/s" in x)) + 1]
    hz_row = hz.splitlines()[hz.splitlines().index(next(x for x in hz.splitlines() if "f Hz" in x)) + 1]
    assert float(hz_row.split()[0]) == pytest.approx(float(rad_row.split()[0]) / (2 * np.pi), rel=1e-3)
    assert hz_row.split()[1:] == rad_row.split()[1:]  # Z, ES, ED, EM stay SI
    with pytest.raises(SystemExit) as bad:  # a usage error: argparse's one line, exit 2
        main(["--units", "furlong", "analyze", "etfe", str(path)])
    assert bad.value.code == 2 and "unknown display unit 'furlong'" in capsys.readouterr().err
