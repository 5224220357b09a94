"""A report as one self-contained HTML file: real tables, figures inline as PNG."""
from __future__ import annotations

import base64
import html

from labbench.readout.escape import one_line
from labbench.report.blocks import Figure, Heading, PageBreak, Paragraph, Table, as_markup

_CSS = """
body{font-family:"Helvetica Neue",Helvetica,Arial,"DejaVu Sans",sans-serif;color:#1d1d1f;
 max-width:62rem;margin:2rem auto;padding:0 1.5rem;line-height:1.45;font-size:15px}
header{border-bottom:2px solid #1d1d1f;margin-bottom:1.5rem}
header h1{font-size:1.9rem;margin:0}header p{margin:.2rem 0 .8rem;color:#555}
h1{font-size:1.5rem;margin:2.5rem 0 .8rem;border-bottom:1px solid #bbb;padding-bottom:.2rem}
h2{font-size:1.2rem;margin:2rem 0 .6rem}h3{font-size:1.05rem;margin:1.4rem 0 .4rem}
table{border-collapse:collapse;margin:.4rem 0 1.4rem;font-size:13.5px;
 font-variant-numeric:tabular-nums;border-top:1.5px solid #1d1d1f;border-bottom:1.5px solid #1d1d1f}
caption{caption-side:top;text-align:left;font-weight:600;padding:.2rem 0 .35rem;font-size:14px}
th{text-align:left;font-weight:600;border-bottom:1px solid #1d1d1f;padding:.3rem .7rem}
td{padding:.25rem .7rem;border-top:1px solid #e3e3e3;vertical-align:top}
td.num,th.num{text-align:right;white-space:nowrap}
table.kv td:first-child{color:#444;padding-right:1.5rem}
table.flags td:nth-child(2){max-width:32rem}
p.note{font-size:12.5px;color:#555;margin:-1rem 0 1.4rem}p.warning{color:#a40000}
figure{margin:1rem 0 1.8rem}figure img{width:100%;height:auto}
figcaption{font-size:13px;color:#444;margin-top:.3rem}
@media print{h1{break-before:page}h1:first-of-type{break-before:auto}
 table,figure{break-inside:avoid}}
"""


def render_html(title: str, subtitle: str, blocks: list) -> str:
    def e(text) -> str:  # an attribute's or the head's text: escaped, controls shown as escapes
        return html.escape(one_line(text))

    out = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{e(title)}</title>"
           f"<style>{_CSS}</style></head><body><header><h1>{as_markup(title)}</h1>"
           f"<p>{as_markup(subtitle)}</p></header>"]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{as_markup(b.text)}</h{b.level}>")
        elif isinstance(b, Paragraph):
            out.append(f"<p class='{b.style}'>{as_markup(b.text)}</p>")
        elif isinstance(b, Table):
            out.append(_table(b))
        elif isinstance(b, Figure):
            data = base64.b64encode(b.png()).decode()
            out.append(f"<figure><img alt='{e(b.caption)}' src='data:image/png;base64,{data}'>"
                       f"<figcaption>{as_markup(b.caption)}</figcaption></figure>")
        elif not isinstance(b, PageBreak):  # a page break means nothing on screen
            raise TypeError(f"unknown report block {type(b).__name__}")
    out.append("</body></html>")
    return "\n".join(out)


def _table(t: Table) -> str:
    numeric = t.numeric()
    kind = "kv" if not t.columns else ("flags" if t.title.startswith("Flags") else "")

    def cls(i):
        return " class='num'" if numeric[i] else ""

    head = "" if not t.columns else "<thead><tr>" + "".join(
        f"<th{cls(i)}>{as_markup(h)}</th>" for i, h in enumerate(t.columns)) + "</tr></thead>"
    body = "".join("<tr>" + "".join(f"<td{cls(i)}>{as_markup(c)}</td>" for i, c in enumerate(row))
                   + "</tr>" for row in t.rows)
    note = f"<p class='note'>{as_markup(t.note)}</p>" if t.note else ""
    return (f"<table class='{kind}'><caption>{as_markup(t.title)}</caption>{head}"
            f"<tbody>{body}</tbody></table>{note}")
