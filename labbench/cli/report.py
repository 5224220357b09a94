"""``labbench report SESSION [SESSION ...] -o DIR``: self-contained HTML and PDF report."""
from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="write an HTML and a PDF report of one or more sessions",
        description="Write one self-contained HTML file (figures embedded) and one PDF "
                    "covering the given sessions: rig, protocol, results, figures of data "
                    "against theory, safety events and loop timing.")
    p.add_argument("sessions", nargs="+", metavar="SESSION", help="session file(s)")
    p.add_argument("-o", "--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--json", action="store_true", help="print the output paths as JSON")
    p.add_argument("--force", action="store_true", help="replace existing report files")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.cli.progress import warner
    from labbench.report import write_report

    html_path, pdf_path = write_report(args.sessions, args.out, force=args.force,
                                       warn=warner("report"))
    if args.json:
        print(json.dumps({"html": str(html_path), "pdf": str(pdf_path)}))
    else:
        print(html_path)
        print(pdf_path)
    return 0
