"""Reports from real simulated runs (runner + sim device) and from damaged or unfinished sessions."""
import base64
import io
import re

import numpy as np
import pytest
from matplotlib import image
from session_recorder import synthetic_stream

from labbench.cli import main
from labbench.errors import UserError
from labbench.report import write_report
from labbench.session_format import SessionWriter

TRUTH = {"m": 0.094, "b": 0.10}  # the default simulated rig


def _record(directory, name, **options):
    from labbench.rig import Rig
    from labbench.runner import run
    from labbench.registry import make_protocol
    from labbench.sim_backend.sim_device import open_sim

    rig = Rig()
    with SessionWriter(directory) as w:
        result = run(open_sim(rig, seed=1), make_protocol(name, **options), [w], rig=rig)
    assert result.status == "success", result.reason
    return w.path, result


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("sessions")
    out = {"chirp-id": _record(d, "chirp-id", duration_s=5.0, f0_hz=0.5),
           "stability": _record(d, "stability", max_step_s=2.0),
           "etfe": _record(d, "etfe", duration_s=10.0, seed=4)}
    return out


def _pngs(html_text):
    blobs = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", html_text)
    return [image.imread(io.BytesIO(base64.b64decode(b)), format="png") for b in blobs]


def test_report_of_real_runs(tmp_path, runs):
    paths = [p for p, _ in runs.values()]
    html_path, pdf_path = write_report(paths, tmp_path / "rep")
    text = html_path.read_text()
    # self-contained: no external resources, every figure decodes as an image
    assert not re.search(r"(src|href)=['\"](?!data:)", text)
    figures = _pngs(text)
    n_expected = 2 * len(paths)  # an overview and a data-vs-theory figure per session
    assert len(figures) >= n_expected and all(f.ndim == 3 and f.shape[0] > 200 for f in figures)
    # the identification table carries the run's own numbers, and they are right
    ident = runs["chirp-id"][1].results["identification"]
    for method in ("l2", "l1"):
        m, b = ident[method]["m"], ident[method]["b"]
        assert f"{m:.6g}" in text and f"{b:.6g}" in text
        assert m == pytest.approx(TRUTH["m"], rel=0.02) and b == pytest.approx(TRUTH["b"], rel=0.02)
    stab = runs["stability"][1].results
    assert f"{stab['exact_boundary']:.4g}" in text and "Probe steps" in text
    for word in ("Rig", "Protocol: chirp-id", "Stability margin", "Events", "Loop timing",
                 "period p99 (ms)"):
        assert word in text
    dev = runs["etfe"][1].results["deviation_vs_sampled"]
    assert f"{dev['median_rel']:.4g}" in text and "Bandwidths" in text
    pdf = pdf_path.read_bytes()
    assert pdf.startswith(b"%PDF") and pdf.rstrip().endswith(b"%%EOF")
    assert len(re.findall(rb"/Type /Page\b", pdf)) >= len(paths) + len(figures)


def test_report_of_unfinished_and_damaged_sessions(tmp_path):
    with SessionWriter(tmp_path) as w:
        for rec in synthetic_stream(800, status=None):
            w(rec)
    raw = w.path.read_bytes()
    w.path.write_bytes(raw[:-40])  # tear the last page
    html_path, pdf_path = write_report(w.path, tmp_path / "rep")
    text = html_path.read_text()
    assert "incomplete" in text and "ends early" in text and "torn chunk" in text
    assert "No results recorded" in text and "force_limit" in text
    assert len(_pngs(text)) == 1 and pdf_path.stat().st_size > 1000


def test_report_cli_and_errors(tmp_path, runs, capsys):
    path = runs["stability"][0]
    assert main(["report", str(path), "-o", str(tmp_path / "r"), "--json"]) == 0
    assert '"pdf"' in capsys.readouterr().out
    assert main(["report", str(tmp_path / "missing.lbsession"), "-o", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
    (tmp_path / "afile").write_text("x")
    assert main(["report", str(path), "-o", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err
    assert "is a file" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(UserError, match="not a labbench session"):
        write_report(tmp_path / "afile", tmp_path / "r2")


def test_numbers_in_tables():
    from labbench.report import fmt

    assert fmt(None) == "-" and fmt(0.0940007571) == "0.094" and fmt(0.0940007571, 6) == "0.0940008"
    assert fmt([1.0, None]) == "[1, -]" and fmt(True) == "yes" and fmt(np.int64(3)) == "3"
    assert fmt(float("inf")) == "inf"
