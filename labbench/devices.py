"""Registry of device backends: name -> "module:factory".

A factory takes ``(rig, **options)`` and returns an open ``labbench.device.Device``.
Imported lazily so a missing optional backend never breaks the others.
"""
from __future__ import annotations

import importlib

from labbench.errors import UserError

DEVICES = {
    "sim": "sim_backend.sim_device:open_sim",
    "sim-canopen": "sim_backend.canopen_peer:open_sim_canopen",
    "sim-serial": "sim_backend.arduino_peer:open_sim_serial",
    "canopen": "drivers.canopen_drive:open_canopen",
    "serial": "drivers.serial_stream:open_serial",
}


def open_device(name: str, rig, **options):
    """Open backend ``name`` for ``rig`` (a ``labbench.rig.Rig``)."""
    try:
        target = DEVICES[name]
    except KeyError:
        raise UserError(f"unknown device {name!r}; choose one of {', '.join(DEVICES)}") from None
    module_name, factory = target.split(":")
    return getattr(importlib.import_module(module_name), factory)(rig, **options)
