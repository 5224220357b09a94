"""Device backends and protocols by name, built in or added by other packages.

Modelled on python-can's interface registry: a built-in table of
``name -> "module:attribute"`` plus the entry-point groups
``labbench.devices`` and ``labbench.protocols``, so a third-party package adds
a backend or a protocol by declaring, in its own pyproject.toml::

    [project.entry-points."labbench.devices"]
    my-rig = "my_package.rig:open_my_rig"      # factory(rig, **options) -> Device

    [project.entry-points."labbench.protocols"]
    sweep = "my_package.sweep:Sweep"           # a labbench.protocol.ProtocolBase

A device backend may also offer a read-only probe for ``labbench devices``
(group ``labbench.device_probes``, same name as the backend):
``probe(rig, fault_reset=False) -> dict``; ``{"no_answer": reason}`` when the
device does not answer. A backend that reads a table of the rig file names its
validator under ``labbench.rig_tables`` (the table's name -> ``check(rig)``, one
``UserError`` for a bad field): ``labbench.rig`` runs it when the file is read, so
every table is refused alike before any device is opened.

Targets are imported only when used, so a backend whose optional packages are
missing never breaks the others. A built-in name cannot be taken over.
"""
from __future__ import annotations

import functools
import importlib
from importlib.metadata import entry_points

from labbench.errors import UserError

DEVICE_GROUP = "labbench.devices"
PROTOCOL_GROUP = "labbench.protocols"
PROBE_GROUP = "labbench.device_probes"
RIG_TABLE_GROUP = "labbench.rig_tables"

_BUILTIN = {
    DEVICE_GROUP: {
        "sim": "labbench.sim_backend.sim_device:open_sim",
        "sim-canopen": "labbench.sim_backend.canopen_peer:open_sim_canopen",
        "sim-serial": "labbench.sim_backend.arduino_peer:open_sim_serial",
        "avr-sim": "labbench.sim_backend.avr_device:open_avr_sim",
        "canopen": "labbench.drivers.canopen_drive:open_canopen",
        "serial": "labbench.drivers.serial_stream:open_serial",
    },
    PROBE_GROUP: {
        "sim-canopen": "labbench.sim_backend.canopen_peer:probe_sim_canopen",
        "canopen": "labbench.drivers.canopen_drive:probe_canopen",
        "serial": "labbench.drivers.serial_probe:probe_serial",
    },
    RIG_TABLE_GROUP: {
        "sim": "labbench.sim_backend.sim_device:sim_options",
        "canopen": "labbench.drivers.canopen_config:CanopenConfig.from_rig",
        "serial": "labbench.drivers.serial_stream:SerialConfig.from_rig",
    },
    PROTOCOL_GROUP: {
        "chirp-id": "labbench.protocols.chirp_id:ChirpId",
        "etfe": "labbench.protocols.white_noise:WhiteNoiseEtfe",
        "stability": "labbench.protocols.stability_probe:StabilityProbe",
        "commission": "labbench.protocols.commission:Commission",
    },
}


@functools.lru_cache(maxsize=None)
def _installed(group: str) -> tuple:
    """(name, "module:attribute") of the installed packages' entry points of ``group``, read
    once a process (each reading scans every installed distribution: 0.2 s on a loaded
    machine, and a campaign looks a protocol up for every point it plans)."""
    return tuple((ep.name, ep.value) for ep in entry_points(group=group))


def _table(group: str) -> dict[str, str]:
    table = dict(_BUILTIN[group])
    for name, value in _installed(group):
        table.setdefault(name, value)
    return table


def _load(group: str, name: str, what: str):
    table = _table(group)
    try:
        module_name, attribute = table[name].split(":")
    except KeyError:
        raise UserError(f"unknown {what} {name!r}; choose one of {', '.join(table)}") from None
    target = importlib.import_module(module_name)
    for part in attribute.split("."):  # "Class.method", as entry points allow
        target = getattr(target, part)
    return target


def device_names() -> list[str]:
    """Every device backend: built-in first, then those of installed packages."""
    return list(_table(DEVICE_GROUP))


def protocol_names() -> list[str]:
    """Every protocol: built-in first, then those of installed packages."""
    return list(_table(PROTOCOL_GROUP))


def device_factory(name: str):
    """The factory ``(rig, **options) -> Device`` of backend ``name``."""
    return _load(DEVICE_GROUP, name, "device")


def open_device(name: str, rig, **options):
    """Open backend ``name`` for ``rig`` (a ``labbench.rig.Rig``)."""
    return device_factory(name)(rig, **options)


def device_probe(name: str):
    """The probe ``(rig, fault_reset=False) -> dict`` of backend ``name``, or None."""
    return _load(PROBE_GROUP, name, "probe") if name in _table(PROBE_GROUP) else None


def rig_table_check(name: str):
    """The validator ``check(rig)`` of the rig file's table ``name``, or None (no backend
    reads it)."""
    table = _table(RIG_TABLE_GROUP)
    return _load(RIG_TABLE_GROUP, name, "rig table") if name in table else None


def protocol_class(name: str):
    """The ``ProtocolBase`` subclass registered as ``name`` (its ``Config`` is its options)."""
    return _load(PROTOCOL_GROUP, name, "protocol")


def make_protocol(name: str, **options):
    """A protocol by name with validated options (one UserError per bad field)."""
    cls = protocol_class(name)
    return cls(cls.Config.from_options(name, options))
