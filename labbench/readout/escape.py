"""User text (rig names, file names, reasons) made safe for each place it is written.

HTML goes through ``html.escape`` of ``one_line`` where it is rendered
(``labbench.report``), so a control character (a terminal escape in a spec or rig name)
shows as its escape there too; the terminal's lines (the CLI's errors, warnings, progress
and summaries) go through ``one_line``; JSON output stays JSON (``json.dumps`` escapes
controls). The two other sinks are here:

* ``one_line``: a header line of a text file (the CSV export's ``# key=value``
  lines) ends at the first line break, so line breaks and other control
  characters are written as backslash escapes;
* ``literal_mpl``: matplotlib parses text between two ``$`` as mathtext, and an
  invalid expression fails the whole drawing (the PDF report), so every ``$``
  is escaped and the text is drawn as typed.
"""
from __future__ import annotations

import re

# C0 and C1 controls, DEL, and the Unicode line and paragraph separators
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(text) -> str:
    r"""``str(text)`` on one line: a newline becomes ``\n``, other controls ``\xNN``/``\uNNNN``."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), str(text))


def literal_mpl(text) -> str:
    """``str(text)`` that matplotlib draws as typed (no mathtext), on one line (``one_line``:
    a control character in a name is drawn as its escape)."""
    return one_line(text).replace("$", r"\$")
