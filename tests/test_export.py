"""Export: HDF5 read back with h5py, CSV read back with numpy (and the analysis loader when present)."""
import json

import h5py
import numpy as np
import pytest
from session_recorder import VE, synthetic_stream

from labbench import records
from labbench.cli import main
from labbench.export import CSV_COLUMNS
from labbench.session_format import SessionWriter


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
    dataio = pytest.importorskip("labbench.analysis.dataio")
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
