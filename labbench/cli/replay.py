"""``labbench replay SESSION [--speed X] [--json]``: feed a recorded stream back through consumers."""
from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay", help="feed a recorded session back through the stream consumers",
        description="Read a session file and feed its records, in order, through the same "
                    "consumers a live run uses; print a summary of the stream.")
    p.add_argument("session", help="session file (.lbsession)")
    p.add_argument("--speed", type=float, default=None,
                   help="pace at this multiple of real time (1 = as recorded); "
                        "default: as fast as possible")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.readout import wording
    from labbench.jsonutil import json_safe
    from labbench.sessions.replay import StreamSummary, replay

    summary = StreamSummary()
    reader = replay(args.session, [summary], speed=args.speed)
    out = summary.as_dict()
    out["session"] = str(reader.path)
    out["damaged_tail"] = reader.problem
    # what the run found, in the words of `labbench run`, the report and the window
    read = wording.of_results(str(out.get("protocol") or ""), (summary.stop or {}).get("results"),
                              summary.start)
    out["readout"] = read.as_dict()
    if args.json:
        print(json.dumps(json_safe(out), indent=2))
    else:
        _print_summary(out)
        for line in read.text_lines():
            print(f"result    {line}")
    if reader.problem:
        from labbench.cli.progress import warner
        from labbench.sessions.session_content import ends_early

        warner("replay")(ends_early(reader.path, reader.problem))
    return 0


def _print_summary(s: dict) -> None:
    print(f"session   {s['session']}")
    print(f"uid       {s['uid']}  protocol {s['protocol']}  rig {s['rig']}")
    print(f"status    {s['status']}" + (f" ({s['reason']})" if s["reason"] else ""))
    print(f"samples   {s['samples']} in {s['pages']} pages, {s['duration_s']:.3f} s, "
          f"{s['dropped_samples']} dropped; max |command| {s['max_abs_command_n']:.3g} N")
    for e in s["events"]:
        t = f"{e['t']:.3f} s" if isinstance(e["t"], (int, float)) else "-"
        print(f"event     {t}  {e['name']}: {e['reason']}")
    if s["timing"]:
        print("timing    " + ", ".join(
            f"{k[:-2]} {v * 1e3:.3g} ms" if k.endswith("_s") and isinstance(v, float) else f"{k} {v}"
            for k, v in s["timing"].items()))
