"""The CANopenNode test drive: a CiA 402 torque drive on CANopenNode v4, built from
``../shared/third_party/CANopenNode`` by the tests (``build``), with our object dictionary
(``dictionary``), CAN transport and node (``CO_driver*``, ``drive.c``), run as a process
of its own on ``udp_multicast`` (``drive_process``). ``start`` starts one.
"""
from __future__ import annotations

import json
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import can

from labbench.rig import rig_from_dict
from labbench.sim_backend.canopen_process import GROUP, ProcessDrive, _free_port, spawn

from canopennode import build as builder

HERE = Path(__file__).resolve().parent


class Watch(can.Listener):
    """Keeps the data frames of the given COB-IDs seen on the bus, in arrival order."""

    def __init__(self, ids):
        self.ids = set(ids)
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id in self.ids and not msg.is_remote_frame:
            with self.lock:
                self.frames.append(msg)

    def seen(self, cob_id: int) -> list[can.Message]:
        with self.lock:
            return [m for m in self.frames if m.arbitration_id == cob_id]


@dataclass
class Running:
    """A drive process, the rig that reaches it, and ``watch``: every EMCY and every
    heartbeat or guarding answer of the drive seen on the bus by a listener of the test's
    own (it reads every frame, so none waits in its socket). ``close()`` ends the process
    and the listener."""

    proc: ProcessDrive
    monitor: object
    rig: object
    tables: dict
    eds: Path
    watch: Watch = field(default=None)
    notifier: can.Notifier = field(default=None)

    def inject_fault(self, code: int) -> None:
        """An internal fault of the drive: torque off, FAULT, EMCY ``code``."""
        self.proc.proc.stdin.write(json.dumps({"fault": code}).encode() + b"\n")
        self.proc.proc.stdin.flush()

    def write_rig(self, path: Path) -> Path:
        """The rig as a TOML file (for the ``labbench`` command line)."""
        lines = []
        for table, values in self.tables.items():
            subs = {k: v for k, v in values.items() if isinstance(v, dict)}  # [canopen.bus]
            lines.append(f"[{table}]")
            lines += [f"{k} = {json.dumps(v)}" for k, v in values.items()  # TOML basic values
                      if k not in subs]
            for sub, sub_values in subs.items():
                lines.append(f"[{table}.{sub}]")
                lines += [f"{k} = {json.dumps(v)}" for k, v in sub_values.items()]
        path.write_text("\n".join(lines) + "\n")
        return path

    def close(self) -> None:
        if self.notifier is not None:
            self.notifier.stop(timeout=1.0)
        self.monitor.shutdown()
        self.proc.close()


def start(variant: str = "event", tables: dict | None = None, use_eds: bool = True,
          node_id: int = 1, seed=None, answer_delay_s: float = 0.0, **options) -> Running:
    """A running drive of ``variant`` (``dictionary.VARIANTS``) and the rig that reaches it
    over ``udp_multicast``.

    ``tables``: rig tables ([rig], [safety], more [canopen] fields ...); ``use_eds``: the
    rig names the EDS the drive serves; ``seed``/``options``: the plant's
    (``canopen_peer.plant_for``); ``answer_delay_s``: the drive takes each SYNC that long
    after it arrived (a slow drive).
    """
    built = builder.build(variant)
    tables = {k: dict(v) for k, v in (tables or {}).items()}
    port = _free_port()
    tables["canopen"] = {"interface": "udp_multicast", "channel": GROUP, "bus": {"port": port},
                         "node_id": node_id, **({"eds": str(built.eds)} if use_eds else {}),
                         **tables.get("canopen", {})}
    rig = rig_from_dict(tables, source="canopennode-rig")
    spec = json.dumps({"lib": str(built.lib), "node_id": node_id, "rig": rig.as_dict(),
                       "seed": seed, "options": options, "port": port,
                       "answer_delay_s": answer_delay_s})
    proc, monitor = spawn([sys.executable, str(HERE / "drive_process.py")], spec, port)
    watch = Watch({0x80 + node_id, 0x700 + node_id})  # EMCY, heartbeat / guarding answers
    running = Running(proc, monitor, rig, tables, built.eds, watch)
    running.notifier = can.Notifier(monitor, [running.watch], timeout=0.05)
    return running
