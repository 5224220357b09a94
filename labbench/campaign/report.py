"""The report of a campaign: its chart first, then one row per point, then the sessions.

Built from the table alone (``labbench.sweep.table``) with the report machinery's blocks
(``labbench.report.blocks``) and renderers: ``campaign.html`` and ``campaign.pdf`` in the
table's charts folder beside it (``NAME.charts``).
A Z-width and a rate study get their own columns (``labbench.campaign.rows``); any other
campaign lists its parameters, status and the protocol's verdict.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from labbench.campaign import figures
from labbench.readout.numfmt import fmt_ci
from labbench.report.blocks import Figure, Heading, PageBreak, Paragraph, Table, fmt, percent

HTML, PDF = "campaign.html", "campaign.pdf"


def _ms(v) -> str:
    return "-" if v is None else fmt(1e3 * v)


def _name(path) -> str:
    return Path(path).name if path else "-"


def _friction_cell(r: dict) -> str:
    """The friction-aware boundary at the probe's swing with its range, or the plan's."""
    k = r.get("zw.k_friction")
    if k is None:
        planned = r.get("pred.k_max_friction")
        return "-" if planned is None else f"{fmt(planned)} (planned)"
    swing = r.get("zw.swing_m")
    at = f" at {fmt(1e3 * swing)} mm" if swing is not None else ""
    return fmt_ci(k, r.get("zw.k_friction_lo"), r.get("zw.k_friction_hi")) + at


def _stops(rows: list[dict]) -> str:
    """Where each probe without a measured boundary stopped, and why (the table's note)."""
    said = [f"#{r['index']}: {r['zw.stopped']}" for r in rows
            if r.get("zw.k_max") is None and r.get("zw.stopped")]
    return ("Points without a measured boundary: " + "; ".join(said) + ".") if said else ""


def _params(r: dict) -> str:
    try:
        p = json.loads(r.get("params_json") or "{}")
    except ValueError:
        return "-"
    return ", ".join(f"{k} = {v}" for k, v in {**p.get("tags", {}), **p.get("params", {})}.items())


ZWIDTH = (["#", "B (N s/m)", "w0 (rad/s)", "status", "K_max measured, 95 % interval (N/m)",
           "exact sampled (N/m)", "measured / exact - 1", "with friction, at the swing (N/m)",
           "measured / with friction - 1", "paper approx. (N/m)",
           "passive, sampled-data (N/m)", "Colgate & Schenkel (N/m)", "observer first (N/m)",
           "lies above"],
          lambda r: [str(r["index"]), fmt(r.get("ve.B")), fmt(r.get("ve.w0_rad_s")), r["status"],
                     fmt_ci(r["zw.k_max"], r.get("zw.ci_lo"), r.get("zw.ci_hi"))
                     if r.get("zw.k_max") is not None else (
                         f"> {fmt(r['zw.k_max_above'])}" if r.get("zw.k_max_above") else "-"),
                     fmt(r.get("pred.k_max")),
                     percent(r.get("zw.rel_error")), _friction_cell(r),
                     percent(r.get("zw.rel_error_friction")), fmt(r.get("pred.k_max_approx")),
                     fmt(r.get("pred.k_passive")), fmt(r.get("pred.k_passive_line")),
                     fmt(r.get("zw.observer_k")), r.get("zw.crossed") or r.get("error") or "-"])
RATE = (["#", "T (ms)", "status", "ED error median meas. / pred.", "ES error median meas. / pred.",
         "within the 95 % band ED / ES", "w_s* meas. / pred. (rad/s)",
         "w_b* meas. / pred. (rad/s)", "K_max fit / pred. (N/m)"],
        lambda r: [str(r["index"]), _ms(r.get("rig.sample_time_s")), r["status"],
                   f"{percent(r.get('acc.ed_median'))} / {percent(r.get('pred.ed_median'))}",
                   f"{percent(r.get('acc.es_median'))} / {percent(r.get('pred.es_median'))}",
                   f"{percent(r.get('acc.ed_in_band'), 3)} / {percent(r.get('acc.es_in_band'), 3)}",
                   f"{fmt(r.get('res.bandwidths.ws_star_measured'))} / "
                   f"{fmt(r.get('res.bandwidths.ws_star_predicted'))}",
                   f"{fmt(r.get('res.bandwidths.wb_star_measured'))} / "
                   f"{fmt(r.get('res.bandwidths.wb_star_predicted'))}",
                   f"{fmt(r.get('acc.k_max_fit'))} / {fmt(r.get('pred.k_max'))}"])
OTHER = (["#", "point", "status", "verdict", "error"],
         lambda r: [str(r["index"]), _params(r), r["status"], r.get("verdict") or "-",
                    r.get("error") or "-"])


def build(directory) -> tuple[str, str, list]:
    """(title, subtitle, blocks) of the campaign whose table is ``directory``."""
    from labbench.sweep import charts, table as tables

    tab = tables.read_table(directory)
    spec = tables.read_spec(directory)
    cols = charts.columns(tab) if tab.num_rows else {}
    rows = figures.table_rows(cols) if cols else []
    campaign = spec.get("campaign") or {}
    name = (spec.get("sweep") or {}).get("name", Path(directory).stem)
    subtitle = (f"{name} on {campaign.get('device', '?')}, rig {campaign.get('rig', '?')}: "
                f"{len(rows)} points in {directory}; written {time.strftime('%Y-%m-%d %H:%M')}")
    blocks: list = [Heading("Chart", 1)]
    drawn = False
    for caption, make in (("Z-width: K_max against B, measured (points, 95 % intervals) and "
                           "predicted for this rig (lines)", figures.zwidth_figure),
                          ("Rate vs accuracy: measured (points) and predicted (lines) against "
                           "the sample time", figures.rate_figure)):
        fig = make(cols) if cols else None
        if fig is not None:
            blocks.append(Figure(caption, fig))
            drawn = True
    if not drawn:
        blocks.append(Paragraph("No chart: the table holds neither a Z-width nor a rate study.",
                                "note"))
    if rows:
        blocks.append(Paragraph(figures.rig_line(rows[0]), "note"))
    zwidth = bool(cols) and bool(figures.zwidth_rows(cols))
    columns, cells = (ZWIDTH if zwidth else
                      RATE if figures.rate_rows(cols) else OTHER) if cols else OTHER
    blocks += [PageBreak(), Heading("Points", 1),
               Table(f"One row per point ({len(rows)})", columns, [cells(r) for r in rows],
                     note=_stops(rows) if zwidth else "")]
    blocks += [PageBreak(), Heading("Sessions", 1),
               Table("The session each point recorded, and the runs that did not finish",
                     ["#", "point", "status", "session", "attempts", "earlier (interrupted)"],
                     [[str(r["index"]), _params(r), r["status"], _name(r.get("session")),
                       fmt(r.get("attempts")), r.get("earlier_sessions") or "-"] for r in rows],
                     note=f"sessions in {Path(rows[0]['session']).parent}" if rows and
                     rows[0].get("session") else "")]
    return "labbench campaign report", subtitle, blocks


def write_campaign_report(directory) -> tuple[Path, Path]:
    """``campaign.html`` and ``campaign.pdf`` in the table's charts folder beside it, not in
    the table (Parquet readers take every file inside it for a part); replaced."""
    from labbench.report.render_html import render_html
    from labbench.report.render_pdf import render_pdf
    from labbench.safe_write import output_folder, replacing
    from labbench.sweep.table import charts_folder

    title, subtitle, blocks = build(directory)
    where = output_folder(charts_folder(directory))
    html_path, pdf_path = where / HTML, where / PDF
    with replacing(html_path, force=True) as tmp:
        tmp.write_text(render_html(title, subtitle, blocks), encoding="utf-8")
    with replacing(pdf_path, force=True) as tmp:
        render_pdf(title, subtitle, blocks, tmp)
    return html_path, pdf_path
