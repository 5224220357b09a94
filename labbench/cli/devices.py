"""``labbench devices [--rig FILE] [--fault-reset] [--json]``: what is configured, what answers.

A CANopen drive (``[canopen]`` in the rig, or the simulated one) is probed
read-only over SDO: identity 0x1018, device type 0x1000, supported modes
0x6502, CiA 402 state 0x6041, NMT state from its heartbeat. ``--fault-reset``
is the operator's fault reset: FAULT -> SWITCH ON DISABLED, never further.
"""
from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "devices", help="list configured devices and probe what answers",
        description="List the device backends, which of them the rig configures, and what "
                    "a CANopen drive answers (identity, device type, supported modes, state).")
    p.add_argument("--rig", default=None, help="rig file (TOML); default: the simulated rig")
    p.add_argument("--fault-reset", action="store_true",
                   help="operator fault reset of the CANopen drive (to SWITCH ON DISABLED only)")
    p.add_argument("--sim", action="store_true",
                   help="with --fault-reset: act on a fresh simulated drive (a demonstration)")
    p.add_argument("--json", action="store_true", help="print the listing as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.jsonutil import json_safe
    from labbench.registry import device_names
    from labbench.rig import load_rig

    rig = load_rig(args.rig)
    if args.fault_reset:
        return _fault_reset(rig, args.sim)
    rows = []
    for name in device_names():
        table = _TABLES.get(name)
        configured = table is None or table in rig.sections
        row = {"device": name, "configured": configured,
               "table": f"[{table}]" if table else "(built in)"}
        if name in ("sim-canopen", "canopen") and configured:
            row["answer"] = _probe(name, rig)
        rows.append(row)
    if args.json:
        print(json.dumps(json_safe({"rig": rig.name, "source": rig.source, "devices": rows}),
                         indent=2))
        return 0
    print(f"rig {rig.name} ({rig.source})")
    for r in rows:
        state = "configured" if r["configured"] else f"not configured (no {r['table']})"
        print(f"{r['device']:<12} {state}")
        if "answer" in r:
            print("             " + _describe(r["answer"]))
    return 0


# Rig table each hardware backend needs (None: nothing to configure).
_TABLES = {"sim": None, "sim-canopen": None, "sim-serial": None,
           "canopen": "canopen", "serial": "serial"}


def _drive(rig, sim: bool):
    """The CANopen driver for the rig's drive, or for a fresh simulated drive (closed with it)."""
    from labbench.drivers.canopen_drive import CanopenConfig, CanopenDrive

    if not sim:
        return CanopenDrive(rig, CanopenConfig.from_section(rig.section("canopen"), source=rig.source))
    from labbench.sim_backend.canopen_peer import sim_config, start_sim_drive

    config = sim_config(rig)
    peer, bus = start_sim_drive(rig, config)
    try:
        drive = CanopenDrive(rig, config, bus=bus)
    except BaseException:
        peer.close()
        raise
    drive.add_close_hook(peer.close)
    return drive


def _probe(name: str, rig) -> dict:
    """Read-only probe; a drive that does not answer is reported, not raised."""
    from labbench.errors import LabbenchError

    try:
        with _drive(rig, sim=name == "sim-canopen") as drive:  # closed even if connect fails
            drive.connect()
            return drive.probe()
    except LabbenchError as exc:
        return {"no_answer": str(exc)}


def _describe(a: dict) -> str:
    if "no_answer" in a:
        return f"no answer: {a['no_answer']}"
    text = (f"node {a['node_id']}: vendor 0x{a['vendor_id']:08X} product 0x{a['product_code']:08X}"
            f" revision 0x{a['revision']:08X} serial {a['serial']}; device type "
            f"0x{a['device_type']:08X} (profile {a['device_type'] & 0xFFFF}); supported modes "
            f"0x{a['supported_modes']:08X} (torque: {', '.join(a['torque_modes']) or 'none'}); "
            f"{a['state']}; NMT {a['nmt_state']}")
    return text + (f"; {a['error_code']}" if "error_code" in a else "")


def _fault_reset(rig, sim: bool) -> int:
    with _drive(rig, sim) as drive:
        drive.connect()
        before = drive.drive_state()
        after = drive.reset_fault()
    print(f"node {drive.config.node_id}: {before.value} -> {after.value}")
    return 0
