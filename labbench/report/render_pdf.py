"""A report as an A4 PDF (reportlab): typeset text, ruled tables that wrap and split
across pages with their header repeated, figures at print resolution, page numbers.

Fonts: DejaVu Sans from matplotlib's own data folder (matplotlib is a dependency),
so every symbol the report uses (ω, ±, ², −) prints, on any machine.
"""
from __future__ import annotations

import io
import re
from pathlib import Path

from matplotlib import get_data_path
from reportlab.lib import colors
from reportlab.lib.enums import TA_RIGHT
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.pdfbase import pdfmetrics
from reportlab.pdfbase.ttfonts import TTFont
from reportlab.platypus import (
    Image,
    KeepTogether,
    Paragraph as RLParagraph,
    SimpleDocTemplate,
    Spacer,
    Table as RLTable,
    TableStyle,
)
from reportlab.platypus import PageBreak as RLPageBreak

from labbench.report.blocks import Figure, Heading, PageBreak, Paragraph, Table, as_markup

FONT, BOLD, ITALIC = "LabbenchSans", "LabbenchSans-Bold", "LabbenchSans-Oblique"
MARGIN = 18 * mm
INK, GREY, RULE = colors.HexColor("#1d1d1f"), colors.HexColor("#555555"), colors.HexColor("#dddddd")
FIGURE_DPI = 200


def _fonts() -> None:
    if FONT in pdfmetrics.getRegisteredFontNames():
        return
    ttf = Path(get_data_path()) / "fonts" / "ttf"
    for name, file in ((FONT, "DejaVuSans.ttf"), (BOLD, "DejaVuSans-Bold.ttf"),
                       (ITALIC, "DejaVuSans-Oblique.ttf")):
        pdfmetrics.registerFont(TTFont(name, str(ttf / file)))
    pdfmetrics.registerFontFamily(FONT, normal=FONT, bold=BOLD, italic=ITALIC, boldItalic=BOLD)


def _styles() -> dict[str, ParagraphStyle]:
    base = ParagraphStyle("body", fontName=FONT, fontSize=8.8, leading=11.6, textColor=INK,
                          spaceAfter=5)
    return {
        "title": ParagraphStyle("title", base, fontName=BOLD, fontSize=18, leading=22, spaceAfter=2),
        "subtitle": ParagraphStyle("subtitle", base, textColor=GREY, spaceAfter=8),
        1: ParagraphStyle("h1", base, fontName=BOLD, fontSize=13.5, leading=17, spaceBefore=4,
                          spaceAfter=6, keepWithNext=1),
        2: ParagraphStyle("h2", base, fontName=BOLD, fontSize=11, leading=14, spaceBefore=10,
                          spaceAfter=4, keepWithNext=1),
        3: ParagraphStyle("h3", base, fontName=BOLD, fontSize=9.5, leading=12, spaceBefore=6,
                          keepWithNext=1),
        "body": base,
        "note": ParagraphStyle("note", base, fontSize=7.4, leading=9.4, textColor=GREY),
        "warning": ParagraphStyle("warning", base, textColor=colors.HexColor("#a40000")),
        "caption": ParagraphStyle("caption", base, fontName=BOLD, fontSize=8.8, spaceAfter=3,
                                  keepWithNext=1),
        "figcaption": ParagraphStyle("figcaption", base, fontName=ITALIC, fontSize=7.6,
                                     leading=9.6, textColor=GREY, spaceAfter=10),
        "cell": ParagraphStyle("cell", base, fontSize=7.6, leading=9.4, spaceAfter=0),
        "cell-num": ParagraphStyle("cell-num", base, fontSize=7.6, leading=9.4, spaceAfter=0,
                                   alignment=TA_RIGHT),
        "head": ParagraphStyle("head", base, fontName=BOLD, fontSize=7.6, leading=9.4, spaceAfter=0),
        "head-num": ParagraphStyle("head-num", base, fontName=BOLD, fontSize=7.6, leading=9.4,
                                   spaceAfter=0, alignment=TA_RIGHT),
    }


def _rl(text) -> str:
    """Block text as reportlab paragraph markup (it spells superscript <super>)."""
    return as_markup(text).replace("<sup>", "<super>").replace("</sup>", "</super>")


def render_pdf(title: str, subtitle: str, blocks: list, path) -> None:
    _fonts()
    st = _styles()
    width = A4[0] - 2 * MARGIN
    story = [RLParagraph(_rl(title), st["title"]), RLParagraph(_rl(subtitle), st["subtitle"])]
    for b in blocks:
        if isinstance(b, Heading):
            story.append(RLParagraph(_rl(b.text), st[min(b.level, 3)]))
        elif isinstance(b, Paragraph):
            story.append(RLParagraph(_rl(b.text), st.get(b.style, st["body"])))
        elif isinstance(b, Table):
            story.extend(_table(b, st, width))
        elif isinstance(b, Figure):
            story.append(_figure(b, st, width))
        elif isinstance(b, PageBreak):
            story.append(RLPageBreak())
        else:
            raise TypeError(f"unknown report block {type(b).__name__}")

    def footer(canvas, doc):
        canvas.saveState()
        canvas.setFont(FONT, 7)
        canvas.setFillColor(GREY)
        canvas.drawString(MARGIN, 10 * mm, title)
        canvas.drawRightString(A4[0] - MARGIN, 10 * mm, f"page {doc.page}")
        canvas.restoreState()

    doc = SimpleDocTemplate(str(path), pagesize=A4, leftMargin=MARGIN, rightMargin=MARGIN,
                            topMargin=MARGIN, bottomMargin=MARGIN + 4 * mm, title=title,
                            author="labbench", subject=subtitle)
    doc.build(story, onFirstPage=footer, onLaterPages=footer)


def _table(t: Table, st: dict, width: float) -> list:
    """Caption, table and note; kept on one page unless long (then split, header repeated)."""
    numeric = t.numeric()
    n = len(numeric)
    rows = ([t.columns] if t.columns else []) + [list(r) + [""] * (n - len(r)) for r in t.rows]
    if not rows or not n:  # nothing known (e.g. a session whose start record was unreadable)
        return [RLParagraph(_rl(t.title), st["caption"]), RLParagraph("-", st["note"]),
                Spacer(1, 7)]
    header = bool(t.columns)
    cells = []
    for k, row in enumerate(rows):
        kind = "head" if header and k == 0 else "cell"
        cells.append([RLParagraph(_rl(c), st[kind + ("-num" if numeric[i] else "")])
                      for i, c in enumerate(row)])
    table = RLTable(cells, colWidths=_widths(rows, header, width, st["cell"].fontSize), repeatRows=1 if header else 0,
                    hAlign="LEFT")
    style = [("VALIGN", (0, 0), (-1, -1), "TOP"),
             ("LEFTPADDING", (0, 0), (-1, -1), 4), ("RIGHTPADDING", (0, 0), (-1, -1), 4),
             ("TOPPADDING", (0, 0), (-1, -1), 1.8), ("BOTTOMPADDING", (0, 0), (-1, -1), 1.8),
             ("LINEABOVE", (0, 0), (-1, 0), 1.1, INK), ("LINEBELOW", (0, -1), (-1, -1), 1.1, INK)]
    if header:
        style.append(("LINEBELOW", (0, 0), (-1, 0), 0.6, INK))
    first = 1 if header else 0
    if len(rows) > first + 1:
        style.append(("LINEBELOW", (0, first), (-1, -2), 0.25, RULE))
    table.setStyle(TableStyle(style))
    parts = [RLParagraph(_rl(t.title), st["caption"]), table]
    if t.note:
        parts += [Spacer(1, 2), RLParagraph(_rl(t.note), st["note"])]
    parts.append(Spacer(1, 7))
    return [KeepTogether(parts)] if len(rows) <= 30 else parts


def _widths(rows, header: bool, width: float, size: float) -> list[float]:
    """Column widths: each column's longest line if they fit; else the columns shrink in
    proportion to their slack above their longest word (the header in bold), so long
    texts wrap and short numbers stay on one line."""
    pad = 8.5

    def text_width(text, bold: bool) -> float:
        return pdfmetrics.stringWidth(text, BOLD if bold else FONT, size)

    plain = [[re.sub(r"<[^>]+>", "", str(c)) for c in r] for r in rows]
    n = len(plain[0])
    natural = [max(text_width(r[i], header and k == 0) for k, r in enumerate(plain)) + pad
               for i in range(n)]
    least = [max(text_width(word, header and k == 0) for k, r in enumerate(plain)
                 for word in r[i].split() or [""]) + pad for i in range(n)]
    excess = sum(natural) - width
    if excess <= 0:
        return natural
    slack = [a - b for a, b in zip(natural, least)]
    if sum(slack) >= excess:
        return [a - s * excess / sum(slack) for a, s in zip(natural, slack)]
    return [w * width / sum(least) for w in least]


def _figure(f: Figure, st: dict, width: float):
    fig = f.figure
    w_in, h_in = fig.get_size_inches()
    img_w = width * f.width
    image = Image(io.BytesIO(f.png(FIGURE_DPI)), width=img_w, height=img_w * h_in / w_in)
    image.hAlign = "LEFT"
    return KeepTogether([image, RLParagraph(_rl(f.caption), st["figcaption"])])
