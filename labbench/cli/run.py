"""``labbench run {chirp-id,etfe,stability,demo}``: run a protocol on a device, record a session.

Protocol options are generated from the protocol's config dataclass: field
``w0_rad_s`` becomes ``--w0-rad-s`` (``none`` for an absent optional value).
``demo`` runs chirp-ID, then the paper's ETFE (K = 50, B = 1, w0 = 125) with the
identified m, b as theory overlay, then writes the report of both sessions.

Exit code: 0 success; 1 a failed run (a device fault, a safety trip, a session that
could not be written); 3 recorded whole but the analysis failed (status "failed",
cause "analysis": the session is kept, ``labbench analyze`` re-runs it); 2 a refused
input; 128 + n a signal.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from dataclasses import fields
from pathlib import Path

from labbench.jsonutil import json_safe
from labbench.registry import device_names, open_device
from labbench.errors import UserError
from labbench.cli.progress import ProgressBar
from labbench.loop.interrupts import StopRequest, stopping
from labbench.rig import load_rig
from labbench.safe_write import editable, output_path

# Config fields the CLI sets itself (from the rig).
_HIDDEN = ("sample_time_s",)
_EXIT = {"success": 0, "failed": 1, "aborted": 130}
ANALYSIS_FAILED = 3  # the recording is whole and kept, its analysis failed (module doc)


def _exit_code(result) -> int:
    return ANALYSIS_FAILED if result.cause == "analysis" else _EXIT.get(result.status, 1)


def register(subparsers) -> None:
    from labbench.registry import protocol_class, protocol_names

    p = subparsers.add_parser("run", help="run a protocol on a device and record a session",
                              description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="protocol", required=True, metavar="{chirp-id,etfe,stability,commission,demo}")
    for name in protocol_names():
        config_cls = protocol_class(name).Config
        sp = sub.add_parser(name, help=(config_cls.__doc__ or name).splitlines()[0])
        _common(sp)
        _config_options(sp, config_cls)
        sp.add_argument("--plant-from", choices=("last-id", "nominal"), default="last-id",
                        help="plant for the precheck and theory when --plant-m-kg/--plant-b are "
                             "absent: the newest chirp-ID of this rig in --out (default), else "
                             "the rig's nominal; or always the nominal")
        if name == "commission":
            sp.add_argument("--write-rig", action="store_true",
                            help="write the measured values into --rig FILE (comments kept, the "
                                 "old file backed up as FILE.bak)")
        sp.set_defaults(func=cmd_run)
    demo = sub.add_parser("demo", help="chirp-ID, then ETFE K=50 B=1 w0=125, then the report")
    _common(demo)
    demo.add_argument("--chirp-duration-s", type=float, default=60.0, help="chirp length [s]")
    demo.add_argument("--etfe-duration-s", type=float, default=120.0, help="white-noise length [s]")
    demo.add_argument("--seed", type=int, default=1, help="white-noise seed (default 1)")
    demo.add_argument("--no-report", action="store_true", help="skip the HTML/PDF report")
    demo.set_defaults(func=cmd_demo)


def _common(sp) -> None:
    sp.add_argument("--device", choices=device_names(), default="sim", help="backend (default sim)")
    sp.add_argument("--rig", metavar="FILE", help="rig TOML file (default: simulated Phantom-like)")
    sp.add_argument("--realtime", action="store_true", help="pace the simulator in real time")
    sp.add_argument("--no-rt", dest="rt", action="store_false", default=None,
                    help="do not ask for real-time scheduling (default: asked for on paced "
                         "devices; rig table [realtime])")
    sp.add_argument("--rt-priority", type=int, metavar="N", help="SCHED_FIFO priority (default 80)")
    sp.add_argument("--out", metavar="DIR", default="sessions", help="session directory (./sessions)")
    sp.add_argument("--port", metavar="PORT", help="with --device serial: the serial port "
                    "(e.g. /dev/ttyACM0; overrides the rig's [serial] port; "
                    "`labbench devices --serial` lists them)")
    sp.add_argument("--skip-commissioning", action="store_true",
                    help="render a spring or damper on real hardware before the rig passed "
                         "`labbench run commission` (for people who know their rig)")
    sp.add_argument("--json", action="store_true", help="print one JSON object: sessions, results")
    sp.add_argument("--can-log", metavar="FILE", default=None,
                    help="CANopen devices: record every CAN frame (.asc, .blf, .log, .trc, .csv)")


def _config_options(sp, config_cls) -> None:
    """One option per config field, typed from its annotation, its help the field's own
    description (``labbench.protocol.field_help``)."""
    from labbench.protocol import field_help

    described = field_help(config_cls)
    for f in fields(config_cls):
        if f.name in _HIDDEN:
            continue
        flag = "--" + f.name.replace("_", "-")
        ann = str(f.type)
        text = described[f.name].replace("%", "%%")
        if ann == "bool":
            sp.add_argument(flag, dest=f.name, action="store_true", default=argparse.SUPPRESS,
                            help=text)
            continue
        if ann.startswith("tuple"):
            kind, metavar = _words, "A,B"
        elif ann.startswith("float"):
            kind, metavar = _number, "X"
        elif ann.startswith("int"):
            kind, metavar = _whole, "N"
        else:
            kind, metavar = _text, "NAME"
        sp.add_argument(flag, dest=f.name, type=kind, default=argparse.SUPPRESS, metavar=metavar,
                        help=text)


def _none(text: str) -> bool:
    return text.strip().lower() in ("none", "off", "")


def _number(text: str):
    if _none(text):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or none, got {text!r}") from None


def _whole(text: str):
    if _none(text):
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number or none, got {text!r}") from None


def _text(text: str):
    return None if _none(text) else text


def _words(text: str) -> tuple:
    return tuple(w.strip() for w in text.split(",") if w.strip())


_COMMON = ("command", "protocol", "func", "device", "rig", "realtime", "out", "json", "plant_from",
           "can_log", "rt", "rt_priority", "port", "verbose", "quiet", "units",
           "skip_commissioning", "write_rig")


def _options(args) -> dict:
    return {k: v for k, v in vars(args).items() if k not in _COMMON}


def last_identified(directory, rig) -> dict | None:
    """m, b of the newest successful chirp-ID session of this rig in ``directory`` (or None)."""
    from labbench.sessions.session_catalogue import last_identified as newest

    def skipped(path, reason):
        print(f"labbench run: warning: skipped {path}: {reason}", file=sys.stderr)

    return newest(directory, rig.name, on_skip=skipped)


def _run_one(args, rig, name: str, options: dict, stop: StopRequest, progress=None,
             consumers=(), device_options: dict | None = None, plant_from: dict | None = None):
    """Make the protocol, open the device, run with a session writer; (result, session path).

    ``progress``: the runner's callback (default: a progress bar on stderr); ``consumers``:
    more record consumers after the session writer; ``device_options``: more options for
    the device (a simulator's); ``plant_from``: where the plant in ``options`` came from, for
    the start record (``{"m", "b", "session"}`` or ``{"m", "b", "nominal": True}``).
    ``labbench campaign`` runs each point through here."""
    from labbench.loop.realtime import RealtimeConfig
    from labbench.runner import run_recorded
    from labbench.registry import make_protocol, protocol_class
    from labbench.sessions.session_catalogue import OWN_PLANT, plant_options
    from labbench.sessions.session_format import session_folder

    # commissioning checks the rig's nominal model itself: never an identified one
    if (getattr(args, "plant_from", "nominal") == "last-id" and name not in OWN_PLANT
            and options.get("plant_m_kg") is None and options.get("plant_b") is None):
        found = last_identified(args.out, rig)
        if found is not None:
            plant_from = found
            options = {**options, **plant_options(found, {f.name for f in fields(protocol_class(name).Config)})}
            friction = f", Fc = {found['coulomb_n']:.4g} N" if "plant_coulomb_n" in options else ""
            print(f"labbench run: using m = {found['m']:.5g} kg, b = {found['b']:.5g} N s/m{friction} "
                  f"identified in {found['session']}", file=sys.stderr)
    protocol = make_protocol(name, sample_time_s=rig.sample_time_s, **options)
    dev_opts = {"seed": protocol.seed, **(device_options or {})}
    if args.realtime:
        dev_opts["realtime"] = True
    if args.can_log:
        if args.device not in ("canopen", "sim-canopen"):
            raise UserError("--can-log records CAN frames: use it with --device canopen or "
                            "sim-canopen")
        log = Path(args.can_log)  # demo: one file per run
        log = log if args.protocol != "demo" else log.with_name(f"{log.stem}-{name}{log.suffix}")
        # streamed as frames arrive (no temporary file), but never over an existing file
        output_path(log, [args.rig] if args.rig else [])
        dev_opts["can_log"] = str(log)
    if args.port:
        if args.device != "serial":
            raise UserError(f"--port is for --device serial, not --device {args.device}")
        dev_opts["port"] = args.port
    rt = RealtimeConfig.from_rig(rig, enabled=getattr(args, "rt", None),
                                 priority=getattr(args, "rt_priority", None))
    session_folder(args.out)  # a folder that takes no new file: refused before the device opens
    device = open_device(args.device, rig, **dev_opts)
    _print_device_notes(device.describe().details)
    with ProgressBar(name) if progress is None else contextlib.nullcontext(progress) as bar:
        # the start record says where the plant came from (the window shows it)
        return run_recorded(device, protocol, args.out, consumers, stop=stop, progress=bar,
                            rig=rig, realtime=rt,  # simulated or not: the description says
                            skip_commissioning=args.skip_commissioning,
                            start_extra={"plant_from": plant_from} if plant_from else None)


def _print_device_notes(details: dict) -> None:
    """What a driver planned and replaced (e.g. a CANopen drive's PDO plan, its fallbacks)."""
    for line in details.get("pdo_plan", ()):
        print(f"labbench run: {line}", file=sys.stderr)
    if "bus_load" in details:
        print(f"labbench run: bus load at 1 Mbit/s {100 * details['bus_load']:.1f} %",
              file=sys.stderr)
    for text in details.get("warnings", ()):
        print(f"labbench run: warning: {text}", file=sys.stderr)


def cmd_run(args) -> int:
    rig = load_rig(args.rig)
    write = getattr(args, "write_rig", False)
    if write:
        if not args.rig:
            raise UserError("--write-rig writes the rig file: give it with --rig FILE")
        editable(args.rig, "rig file")  # before the device opens: not after the whole run
    stop = StopRequest()
    with stopping(stop):  # SIGINT/SIGTERM/SIGHUP: zero force, session closed "aborted"
        result, path = _run_one(args, rig, args.protocol, _options(args), stop)
    out = {"protocol": args.protocol, "status": result.status, "reason": result.reason,
           "cause": result.cause,
           "sessions": [str(path)] if path else [], "session": str(path) if path else None,
           "results": result.results,
           "timing": result.timing}
    _say_failure(result, path, rig.sample_time_s)
    code = stop.exit_code or _exit_code(result)
    if write and result.status == "success" and "error" not in result.results:
        code = _write_rig(args.rig, result, path, out) or code
    _print(args, out, [(args.protocol, result, path)])
    return code


def _say_failure(result, path, T: float) -> None:
    """One line on stderr when the device or the recording ended the run (the summary on
    stdout, or the JSON, follows as for any run)."""
    if result.cause == "recording":
        print(f"labbench run: error: {result.reason}", file=sys.stderr)
    elif result.cause == "analysis":
        print(f"labbench run: error: {result.reason} (session {path})", file=sys.stderr)
    elif result.cause == "device":
        what = result.reason.removeprefix("fault: ").removeprefix("device fault: ")
        kept = f"the session {path} holds the run up to it" if path else "no session kept"
        print(f"labbench run: error: device fault after {result.n_samples * T:.1f} s: {what}; "
              f"force zeroed, {kept}", file=sys.stderr)


def _write_rig(rig_file: str, result, path, out: dict) -> int | None:
    """``--write-rig``: the measured values into the rig file; a refusal (read-only since
    the check, a full disk) is one line and exit 2, the JSON summary printed all the same."""
    from datetime import datetime, timezone

    from labbench.commissioning import changes_to_write, write_rig

    fields = changes_to_write(result.results, str(path),
                              datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))
    try:
        backup = write_rig(rig_file, fields)
    except UserError as exc:
        out["rig_written"] = {"fields": fields, "backup": None, "error": str(exc)}
        print(f"labbench run: error: {exc}; the measured values are in the session {path}",
              file=sys.stderr)
        return 2
    real = os.path.realpath(rig_file)
    out["rig_written"] = {"fields": fields, "backup": str(backup) if backup else None,
                          "file": real}
    link = f" (a link: its real file {real} edited)" if os.path.islink(rig_file) else ""
    print(f"labbench run: {rig_file}{link}: " + (f"wrote {', '.join(fields)} (old file {backup})"
                                                 if backup else "nothing to change"),
          file=sys.stderr)
    return None


def cmd_demo(args) -> int:
    """Chirp-ID, then ETFE with the paper's spring-damper and the identified m, b, then the report."""
    for name in ("chirp_duration_s", "etfe_duration_s"):
        if not getattr(args, name) > 0:
            raise UserError(f"--{name.replace('_', '-')} must be positive")
    rig = load_rig(args.rig)
    stop = StopRequest()
    runs = []
    with stopping(stop):
        chirp, chirp_path = _run_one(args, rig, "chirp-id",
                                     {"duration_s": args.chirp_duration_s}, stop)
    _say_failure(chirp, chirp_path, rig.sample_time_s)
    runs.append(("chirp-id", chirp, chirp_path))
    out = {"protocol": "demo", "sessions": [str(chirp_path)], "results": {"chirp-id": chirp.results}}
    m, b = chirp.results.get("m"), chirp.results.get("b")
    fc, fc_ci = chirp.results.get("coulomb"), chirp.results.get("coulomb_ci95")
    if chirp.status != "success" or m is None or b is None or not m > 0 or b < 0:
        out.update(status="failed", reason=f"chirp-ID did not give a plant: {chirp.reason}")
        _print(args, out, runs)
        return stop.exit_code or _exit_code(chirp) or 1
    with stopping(stop):
        etfe, etfe_path = _run_one(args, rig, "etfe", {
            "ve": "spring-damper", "K": 50.0, "B": 1.0, "w0_rad_s": 125.0, "td_s": 0.0,
            "duration_s": args.etfe_duration_s, "seed": args.seed, "plant_m_kg": m,
            "plant_b": b, "plant_coulomb_n": fc, "plant_coulomb_ci95": fc_ci if fc is not None else None},
            stop, plant_from={"m": m, "b": b, "session": str(chirp_path),
                              **({"coulomb_n": fc, "coulomb_ci95": fc_ci} if fc is not None else {})})
    _say_failure(etfe, etfe_path, rig.sample_time_s)
    runs.append(("etfe", etfe, etfe_path))
    out["sessions"].append(str(etfe_path))
    out["results"]["etfe"] = etfe.results
    out.update(status=etfe.status, reason=etfe.reason)
    if etfe.status == "success" and not args.no_report:
        from labbench.report import write_report

        try:
            html, pdf = write_report([chirp_path, etfe_path], args.out)
        except UserError as exc:  # e.g. a full disk: the sessions are kept, the summary said
            out["report"] = {"error": str(exc)}
            print(f"labbench run: error: {exc}", file=sys.stderr)
            _print(args, out, runs)
            return stop.exit_code or 2
        out["report"] = {"html": str(html), "pdf": str(pdf)}
    _print(args, out, runs)
    return stop.exit_code or _exit_code(etfe)


def _print(args, out: dict, runs) -> None:
    """The run's summary: every surface's words from ``labbench.readout.wording`` (of the session as
    recorded, when there is one); ``--json``: the same under ``readout`` (one per run)."""
    from labbench.readout import wording
    from labbench.sessions import session_content

    reads = {name: session_content.readout_of(path) if path else wording.of_results(name, result.results)
             for name, result, path in runs}
    if args.json:
        key = "readout" if len(reads) == 1 else "readouts"
        body = next(iter(reads.values())).as_dict() if len(reads) == 1 else \
            {name: r.as_dict() for name, r in reads.items()}
        print(json.dumps(json_safe({**out, key: body}), allow_nan=False))
        return
    for name, result, path in runs:
        print(f"{name}: {result.status} ({result.reason}); session {path}")
        for line in reads[name].text_lines():
            print("  " + line)
    if out.get("report", {}).get("html"):
        print(f"report: {out['report']['html']}  {out['report']['pdf']}")
    sys.stdout.flush()



