"""Reports from real simulated runs (runner + sim device) and from damaged or unfinished sessions.

The PDF is read back with pypdf: page 1 must be the summary (what ran, the verdict,
the flags), the configuration must come last.
"""
import base64
import io
import re

import numpy as np
import pytest
from matplotlib import image
from pypdf import PdfReader
from session_recorder import synthetic_stream

from labbench import records
from labbench.model import linear
from labbench.cli import main
from labbench.errors import UserError
from labbench.report import write_report
from labbench.readout.numfmt import fmt_ci
from labbench.report.blocks import Figure, PageBreak, Table
from labbench.report.content import build
from labbench.sessions.session_format import SessionWriter
from labbench.model.ve import Plant, VirtualEnvironment
from sim_sessions import TRUTH, record_session


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("sessions")
    out = {"chirp-id": record_session(d, "chirp-id", duration_s=5.0, f0_hz=0.5),
           "stability": record_session(d, "stability", max_step_s=2.0),
           "etfe": record_session(d, "etfe", duration_s=10.0, seed=4, plant_m_kg=TRUTH["m"],
                           plant_b=TRUTH["b"])}
    return out


def _pngs(html_text):
    blobs = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", html_text)
    return [image.imread(io.BytesIO(base64.b64decode(b)), format="png") for b in blobs]


def _pages(pdf_path) -> list[str]:
    return [" ".join(p.extract_text().split()) for p in PdfReader(pdf_path).pages]


def test_report_of_real_runs(tmp_path, runs):
    paths = [p for p, _ in runs.values()]
    html_path, pdf_path = write_report(paths, tmp_path / "rep")
    text = html_path.read_text()
    # self-contained: no external resources, every figure decodes as an image
    assert not re.search(r"(src|href)=['\"](?!data:)", text)
    figures = _pngs(text)
    # the summary overlay, a data-vs-theory figure per session, a channel overview per session
    assert len(figures) >= 1 + 2 * len(paths)
    assert all(f.ndim == 3 and f.shape[0] > 200 for f in figures)
    # the identification table carries the run's own numbers, and they are right
    ident = runs["chirp-id"][1].results["identification"]
    for method in ("l2", "l1"):
        m, b = ident[method]["m"], ident[method]["b"]
        assert f"{m:.6g}" in text and f"{b:.6g}" in text
        assert m == pytest.approx(TRUTH["m"], rel=0.02) and b == pytest.approx(TRUTH["b"], rel=0.02)
    stab = runs["stability"][1].results
    assert f"{stab['exact_boundary']:.4g}" in text and "Probe steps" in text
    for word in ("Rig", "Protocol settings (chirp-id)", "Pre-check", "Events", "Loop timing",
                 "period p99 (ms)", "What ran", "lags", "Bandwidths"):  # "Flags and what to do" or "No flags"
        assert word in text
    assert "<pre" not in text and "monospace" not in text  # typeset, not dumped

    pages = _pages(pdf_path)
    first = pages[0]
    assert "labbench report" in first and "Summary" in first
    for what in ("What ran", "Identified device", "Rendered impedance against the exact sampled",
                 "Stability boundary", "Kmax (exact sampled)", "loop delay td",
                 "Effective stiffness ES", "verdict: ETFE", "below", "not resolved"):
        assert what in first, what
    # m with its interval, on page 1, as the CLI and the window write it
    assert fmt_ci(ident["l2"]["m"], *ident["l2"]["ci95"]["m"], "kg") in first
    assert "Details" not in first and "Appendix" not in first
    # the configuration comes last, in the appendix only
    appendix = next(i for i, p in enumerate(pages) if "Appendix: configuration" in p)
    assert appendix > 1 and "Protocol settings" in pages[appendix]
    assert not any("Protocol settings" in p or "Safety envelope" in p for p in pages[:appendix])
    assert all("Loop timing" not in p for p in pages[appendix:])


def test_bandwidths_are_predicted_by_the_sampled_theory(runs):
    """Page 1's predicted wb* is read off the exact sampled model, not w0 (125 rad/s)."""
    path, result = runs["etfe"]
    ve = VirtualEnvironment("spring-damper", 50.0, 1.0, 125.0, 0.001, 0.0)
    predicted = linear.predicted_bandwidths(Plant(TRUTH["m"], TRUTH["b"]), ve)
    assert predicted["wb_star"] == pytest.approx(72.57, abs=0.05)  # the paper demo's
    assert result.results["bandwidths"]["wb_star_predicted"] == pytest.approx(predicted["wb_star"])
    assert result.results["bandwidths"]["wb_star_w0"] == 125.0
    summary = _summary(build([path]))
    table = next(b for b in summary if isinstance(b, Table) and b.title.startswith("Rendered"))
    row = next(r for r in table.rows if str(r[0]) == "w_b*")
    measured, theory_value = (float(part.split(" = ")[1].split()[0]) for part in row[1].split("; "))
    assert theory_value == pytest.approx(predicted["wb_star"], rel=1e-3)
    # a 10 s record resolves the damping fall to within a few rad/s of the sampled theory
    assert measured == pytest.approx(theory_value, rel=0.05)


def _summary(report) -> list:
    return report.blocks[:next(i for i, b in enumerate(report.blocks) if isinstance(b, PageBreak))]


def test_sessions_are_overlaid_in_one_figure(tmp_path):
    """Three delays on one ES/ED/EM figure, one colour per session (the paper's Figure 8)."""
    delays = (0.0, 0.002, 0.005)
    paths = [record_session(tmp_path, "etfe", duration_s=5.0, seed=3, td_s=td, plant_m_kg=TRUTH["m"],
                     plant_b=TRUTH["b"])[0] for td in delays]
    summary = _summary(build(paths))
    overlays = [b for b in summary if isinstance(b, Figure)]
    assert len(overlays) == 1
    es, ed, em = overlays[0].figure.axes
    colors = {line.get_color() for line in es.get_lines()}
    assert len(es.get_lines()) == 6 and len(colors) == 3  # theory + measurement per session
    # the delay lowers the low-frequency damping (paper sec. 3.3): ED at the lowest point
    # of each session's theory falls with td
    theory_lines = [line for line in ed.get_lines() if line.get_linestyle() == "-"]
    low = [line.get_ydata()[0] for line in theory_lines]
    assert low[0] > low[1] > low[2]
    margin = next(b for b in summary if isinstance(b, Table) and b.title.startswith("Rendered"))
    assert margin.columns[1:] == ["#1 etfe", "#2 etfe", "#3 etfe"]
    # the loop delay on page 1 is measured (closed-loop fit of Z), and it is the true one:
    # the simulator adds no latency, so the loop delay is the VE's td (0.05 ms = 1/20 sample)
    delays = next(r[1:] for r in margin.rows if r[0] == "loop delay td")
    for text, td in zip(delays, (0.0, 2.0, 5.0), strict=True):
        assert "fitted to Z" in text and float(text.split(" ms")[0]) == pytest.approx(td, abs=0.05)


def test_report_of_unfinished_and_damaged_sessions(tmp_path):
    with SessionWriter(tmp_path) as w:
        records.fan_out(synthetic_stream(800, status=None), [w])
    raw = w.path.read_bytes()
    w.path.write_bytes(raw[:-40])  # tear the last page
    html_path, pdf_path = write_report(w.path, tmp_path / "rep")
    text = html_path.read_text()
    assert "incomplete" in text and "ends early" in text and "torn chunk" in text
    assert "no results recorded" in text and "force_limit" in text
    assert len(_pngs(text)) == 1 and pdf_path.stat().st_size > 1000
    first = _pages(pdf_path)[0]
    assert "Flags and what to do" in first and "ends early" in first


def test_session_text_is_escaped(tmp_path):
    """A rig name with markup stays text in the HTML and the PDF."""
    hostile = "<b>rig</b> & <script>alert(1)</script>"
    with SessionWriter(tmp_path) as w:
        for rec in synthetic_stream(800):
            if rec["kind"] == "start":
                rec = {**rec, "rig": {**rec.get("rig", {}), "name": hostile}}
            w(rec)
    html_path, pdf_path = write_report(w.path, tmp_path / "rep")
    text = html_path.read_text()
    assert "<script>" not in text and "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    assert hostile in _pages(pdf_path)[0]


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
    assert Table("t", ["a", "b"], [["x", "1.5"], ["y", "-"]]).numeric() == [False, True]
