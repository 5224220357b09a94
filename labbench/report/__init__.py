"""Run reports: one self-contained HTML file and one A4 PDF with the same content.

One module per job: ``blocks`` (the content as plain data: headings, paragraphs,
tables, figures, flags; what a protocol contributes), ``session`` (a session as a
report reads it), ``content`` (what the report says and in which order: summary
on page 1, details, configuration appendix; each protocol adds its own part via
``ProtocolBase.report_sections``), ``render_html`` and ``render_pdf``.
"""
from __future__ import annotations

from pathlib import Path

from labbench.errors import UserError
from labbench.report.blocks import fmt

__all__ = ["write_report", "fmt"]


def write_report(session_path, out_dir, force: bool = False, warn=None) -> tuple[Path, Path]:
    """Write ``<name>.html`` and ``<name>.pdf`` into ``out_dir`` for one session or a list.

    Returns ``(html_path, pdf_path)``. Raises UserError for a missing or foreign
    session file or an unusable output folder (created if missing, never its
    parents); existing outputs are replaced only with ``force``, each atomically
    (``labbench.safe_write``). ``warn(line)``: a session read up to a damaged record (the
    report flags it too).
    """
    from labbench.report.content import build
    from labbench.report.render_html import render_html
    from labbench.report.render_pdf import render_pdf
    from labbench.safe_write import new_folder, output_path, replacing

    paths = [session_path] if isinstance(session_path, (str, Path)) else list(session_path)
    if not paths:
        raise UserError("no session given")
    out = Path(out_dir)
    stem = Path(paths[0]).stem + (f"+{len(paths) - 1}" if len(paths) > 1 else "")
    html_path, pdf_path = out / f"{stem}.html", out / f"{stem}.pdf"
    if out.exists() and not out.is_dir():
        raise UserError(f"output {out} is a file, not a directory")
    if out.is_dir():  # before the work: refuse what would be refused at the end
        for target in (html_path, pdf_path):
            output_path(target, paths, force)
    elif not out.parent.is_dir():
        raise UserError(f"cannot create output folder {out}: {out.parent} does not exist "
                        "(labbench creates no folders you did not name)")
    report = build(paths, warn)
    with new_folder(out):  # removed again if it was made for this report and stays empty
        with replacing(html_path, paths, force) as tmp:  # a refused write: one UserError
            tmp.write_text(render_html(report.title, report.subtitle, report.blocks),
                           encoding="utf-8")
        with replacing(pdf_path, paths, force) as tmp:
            render_pdf(report.title, report.subtitle, report.blocks, tmp)
    return html_path, pdf_path
