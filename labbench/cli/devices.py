"""``labbench devices [--rig FILE] [--fault-reset] [--serial] [--json]``: what is configured,
what answers.

Each backend the registry offers a probe for (``labbench.registry.device_probe``)
and the rig configures is asked, read-only, what it is: for a CANopen drive
the capability report (identity, device type, CiA 402 state, torque modes,
the planned PDO mapping, how it watches the host, bus load, error history
0x1003, every obstacle and warning); for a serial board what it sends, read with the
rig's ``[serial]`` table as a run reads it (``labbench.drivers.serial_probe``: the first
lines, the period, whether the count moves, and the one-line refusal when the table
cannot read it). "no answer" (nothing on the bus answered)
is told apart from an object the drive says it does not have ("absent").
A probe that raises does not hide the others: its row says what went wrong
in one line. Exit code, from all the rows: 2 when a probe found a bad
setting (``UserError``, or a serial board the rig's table cannot read), else 1 when
one failed otherwise or none of the
configured hardware answers (with no hardware configured: no simulated
device answers), else 0. ``--fault-reset`` is the operator's fault reset:
FAULT -> SWITCH ON DISABLED, never further.

``--serial`` lists the serial ports of this computer (pyserial's
``serial.tools.list_ports``) with what the operating system says about them,
to find the port for ``labbench run ... --device serial --port PORT``.

``--timing [SECONDS]`` is the timing preflight (``labbench.loop.preflight``): the device
(``--device``, default the rig's CANopen drive, else its serial board) opened paced,
enabled at zero force (unless ``[preflight] enable = false``), the loop's own calls for
SECONDS (default ``[preflight] seconds``, 10) under the rig's real-time settings; then
one verdict on the rig's stale limit and sample time, and what to change. ``--write-rig``
writes the suggested limits into the rig file (comments kept, ``FILE.bak`` first).
"""
from __future__ import annotations

import json

# Rig table each hardware backend needs (absent: nothing to configure).
_TABLES = {"canopen": "canopen", "serial": "serial"}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "devices", help="list configured devices and probe what answers",
        description="List the device backends, which of them the rig configures, and what "
                    "each answers (for a CANopen drive: a capability report).")
    p.add_argument("--rig", default=None, help="rig file (TOML); default: the simulated rig")
    p.add_argument("--fault-reset", action="store_true",
                   help="operator fault reset of the CANopen drive (to SWITCH ON DISABLED only)")
    p.add_argument("--sim", action="store_true",
                   help="with --fault-reset: act on a fresh simulated drive (a demonstration)")
    p.add_argument("--serial", action="store_true",
                   help="list the serial ports of this computer (for --device serial --port)")
    p.add_argument("--json", action="store_true", help="print the listing as JSON")
    p.add_argument("--timing", nargs="?", const="", default=None, metavar="SECONDS",
                   help="timing preflight: run the loop's calls on the device for SECONDS "
                        "(default [preflight] seconds, 10) and say whether this PC and bus "
                        "hold the rig's stale limit and sample time")
    p.add_argument("--device", default=None,
                   help="with --timing: the backend to measure (default: canopen if the rig "
                        "has [canopen], else serial)")
    p.add_argument("--write-rig", action="store_true",
                   help="with --timing: write the suggested limits into the rig file "
                        "(comments kept, FILE.bak first)")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.errors import DeviceConnectionError, UserError
    from labbench.jsonutil import json_safe
    from labbench.registry import device_names, device_probe
    from labbench.rig import load_rig

    if args.serial:
        return _list_serial(args.json)
    rig = load_rig(args.rig)
    if args.timing is not None:
        return _timing(args, rig)
    if args.write_rig or args.device:
        raise UserError("--write-rig and --device go with --timing")
    if args.fault_reset:
        result = device_probe("sim-canopen" if args.sim else "canopen")(rig, fault_reset=True)
        if "no_answer" in result:
            raise DeviceConnectionError(result["no_answer"])
        before, after = result["reset"]
        print(f"node {result['node_id']}: {before} -> {after}")
        return 0
    rows = []
    for name in device_names():
        table = _TABLES.get(name)
        configured = table is None or table in rig.sections
        row = {"device": name, "configured": configured,
               "table": f"[{table}]" if table else "(built in)"}
        if configured:
            row.update(_probe(name, rig))
        rows.append(row)
    status = _status(rows)
    for r in rows:
        r.pop("exit", None)
    if args.json:
        print(json.dumps(json_safe({"rig": rig.name, "source": rig.source, "devices": rows}),
                         indent=2))
        return status
    print(f"rig {rig.name} ({rig.source})")
    for r in rows:
        state = "configured" if r["configured"] else f"not configured (no {r['table']})"
        print(f"{r['device']:<12} {state}")
        lines = [f"error: {r['error']}"] if "error" in r else _describe(r.get("answer"))
        for line in lines:
            print("             " + line)
    return status


# The rig table whose stale_periods a backend uses.
_STALE_TABLE = {"canopen": "canopen", "sim-canopen": "canopen", "serial": "serial",
                "sim-serial": "serial", "avr-sim": "serial"}


def _timing(args, rig) -> int:
    """``--timing``: the preflight's numbers and verdict (module doc)."""
    import sys

    from labbench.commissioning import write_tables
    from labbench.errors import UserError
    from labbench.jsonutil import json_safe
    from labbench.loop.preflight import PreflightConfig, checked_seconds, judge, lines, measure, \
        rig_changes
    from labbench.loop.realtime import RealtimeConfig
    from labbench.registry import open_device

    config = PreflightConfig.from_rig(rig)
    seconds = checked_seconds(args.timing) if args.timing else config.seconds
    if args.write_rig and not args.rig:
        raise UserError("--write-rig writes the rig file: give it with --rig FILE")
    if args.write_rig:
        from labbench.safe_write import editable

        editable(args.rig, "rig file")  # before the measurement: not after it
    name = args.device or next((t for t in ("canopen", "serial") if t in rig.sections), None)
    if name is None:
        raise UserError("the rig configures no hardware ([canopen] or [serial]): name the "
                        "backend to measure with --device (e.g. --device sim-canopen)")
    print(f"labbench devices: measuring {name} for {seconds:g} s ...", file=sys.stderr)
    with open_device(name, rig, realtime=True) as device:
        m = measure(device, rig, seconds, RealtimeConfig.from_rig(rig), enable=config.enable,
                    warn=lambda line: print(line, file=sys.stderr))
    judged = judge(m)
    changes = rig_changes(m, judged, _STALE_TABLE.get(name, ""))
    written, code = None, 0
    if args.write_rig and changes:
        try:
            backup = write_tables(args.rig, changes)
        except UserError as exc:  # refused since the check (a full disk): the numbers stay
            written, code = {"changes": changes, "error": str(exc)}, 2
            print(f"labbench devices: error: {exc}", file=sys.stderr)
        else:
            written = {"changes": changes, "backup": str(backup) if backup else None}
    if args.json:
        print(json.dumps(json_safe({"rig": rig.name, "source": rig.source, "preflight": m,
                                    **judged, "rig_changes": changes, "written": written}),
                         indent=2))
        return code
    print("\n".join(lines(m, judged)))
    for table, fields in changes.items():
        said = ", ".join(f"{k} = {v:g}" for k, v in fields.items())
        print(f"  rig change: [{table}] {said}" + (" (written)" if written and not code else
                                                   " (--write-rig writes it)"))
    if written and written.get("backup"):
        print(f"  the old rig file is {written['backup']}")
    return code


def _probe(name: str, rig) -> dict:
    """``{"answer": ...}`` of the backend's probe (none: {}), or ``{"error": one line,
    "exit": 1 or 2}`` whatever it raised."""
    from labbench.errors import LabbenchError, UserError
    from labbench.registry import device_probe

    try:
        probe = device_probe(name)
        return {} if probe is None else {"answer": probe(rig)}
    except Exception as exc:  # noqa: BLE001 - one backend's failure is its row, not the listing's
        text = " ".join(str(exc).split())
        if not isinstance(exc, LabbenchError):  # not one of ours: say what it is
            text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
        return {"error": text, "exit": 2 if isinstance(exc, UserError) else 1}


def _status(rows: list[dict]) -> int:
    """The exit code of the listing (module doc), from every row."""
    worst = max((r["exit"] for r in rows if "exit" in r), default=0)
    if any("refused" in r.get("answer", {}) and "no_answer" not in r["answer"] for r in rows):
        worst = max(worst, 2)  # the board answers, but not as the rig's table says
    if worst:
        return worst
    probed = [r for r in rows if "answer" in r]
    hardware = [r for r in probed if not r["device"].startswith("sim")] or probed
    return 0 if not hardware or any("no_answer" not in r["answer"] for r in hardware) else 1


def serial_ports() -> list[dict]:
    """Every serial port the OS reports: device, description, hardware id, USB ids."""
    from serial.tools import list_ports

    out = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        usb = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None and p.pid is not None else None
        out.append({"device": p.device, "description": p.description, "hwid": p.hwid,
                    "usb_id": usb, "manufacturer": p.manufacturer, "serial_number": p.serial_number})
    return out


def _list_serial(as_json: bool) -> int:
    ports = serial_ports()
    if as_json:
        print(json.dumps({"serial_ports": ports}, indent=2))
        return 0
    if not ports:
        print("no serial ports found")
    for p in ports:
        extra = ", ".join(x for x in (p["manufacturer"], p["usb_id"] and f"USB {p['usb_id']}",
                                      p["serial_number"] and f"serial {p['serial_number']}") if x)
        print(f"{p['device']:<16} {p['description']}" + (f" ({extra})" if extra else ""))
    return 0


def _describe_serial(a: dict) -> list[str]:
    """A serial board's answer (``labbench.drivers.serial_probe``) for people."""
    from labbench.readout.numfmt import fmt

    s = a["stream"]
    out = [f"port {a['port']} at {a['baudrate']} baud: {a['bytes']} bytes in "
           f"{a['seconds']:g} s"]
    if a["first_lines"]:
        out.append("first lines: " + "  ".join(f"`{ln}`" for ln in a["first_lines"]))
    layout = f", fields {json.dumps(s['fields'])}" if s["fields"] else ""
    out.append(f"stream: {s['format']}{layout}; time from the {s['time']}")
    if s["period_s"]:
        steps = (f" (steps {fmt(s['steps_s'][0] * 1e3, 4)} to {fmt(s['steps_s'][1] * 1e3, 4)} "
                 f"ms over {s['lines']} lines)" if s["steps_s"] else f" (over {s['lines']} lines)")
        out.append(f"period: {fmt(s['period_s'] * 1e3, 4)} ms{steps}")
    c = a.get("counts")
    if c:
        moved = (f"moving, {c['min']} .. {c['max']} (first {c['first']}, last {c['last']})"
                 if c["moving"] else "still" + (f" at {c['first']}" if "first" in c else "")
                 + ": move the handle to see it count")
        out.append(f"counts over {c.get('seconds', 0):g} s: {c['n']} samples, {moved}"
                   + (f"; then {c['error']}" if "error" in c else ""))
    out.append(f"refused: {a['refused']}" if "refused" in a else
               "ok: the rig's [serial] table reads this board")
    return out


def _hex(value, digits: int = 8) -> str:
    return "absent" if value is None else f"0x{value:0{digits}X}"


def _describe(a: dict | None) -> list[str]:
    if a is None:
        return []
    if a.get("kind") == "serial":
        return _describe_serial(a)
    if "no_answer" in a:
        return [f"no answer: {a['no_answer']}"]
    dt = a["device_type"]
    lines = [f"node {a['node_id']} answered ({a['source']}): vendor {_hex(a['vendor_id'])} "
             f"product {_hex(a['product_code'])} revision {_hex(a['revision'])} serial "
             f"{_hex(a['serial'])}",
             f"device type {_hex(dt)}" + (f" (profile {dt & 0xFFFF})" if dt is not None else "")
             + f"; supported modes {_hex(a['supported_modes'])} (torque: "
             f"{', '.join(a['torque_modes']) or 'none'})",
             f"{a['state']}; NMT {a['nmt_state']}" + (f"; {a['error_code']}"
                                                      if "error_code" in a else ""),
             "error history 0x1003: " + (", ".join(f"0x{e:08X}" for e in a["error_history"])
                                         or "empty or absent")]
    lines += [f"{k}: {v}" for k, v in a["capabilities"].items()]
    lines += ["PDO plan:"] + [f"  {p}" for p in a["plan"]]
    load = a["bus_load"]
    lines.append(f"bus load at 1 Mbit/s: {100 * load['load_nominal']:.1f} % nominal, "
                 f"{100 * load['load_worst']:.1f} % worst-case stuffing")
    lines += [f"obstacle: {o}" for o in a["obstacles"]]
    if a.get("rig_lines"):
        lines += ["rig lines that would make it usable:"] + [f"  {x}" for x in a["rig_lines"]]
    lines += [f"warning: {w}" for w in a["warnings"]]
    return lines
