"""Every registered backend keeps the device contract (labbench.device).

Each backend that runs without hardware is opened through the registry and
checked against ``Device`` and the optional abilities it offers; each one that
needs hardware must fail to open with a one-line LabbenchError, not a traceback.
"""
from __future__ import annotations

import pytest

from labbench.device import Device, DeviceDescription, DeviceStatus, RawReading, StatusReporting
from labbench.errors import LabbenchError
from labbench.registry import device_names, open_device
from labbench.rig import Rig, rig_from_dict

# avr-sim: the reference firmware on an emulated AVR (skips without the toolchain).
SIMULATED = [n for n in device_names() if n.startswith("sim") or n == "avr-sim"]
HARDWARE = {"canopen": {"canopen": {"interface": "virtual", "channel": "conformance-nobody",
                                    "sdo_timeout_s": 0.05}},
            "serial": {"serial": {"port": "/nonexistent/tty"}}}


def test_every_builtin_backend_is_covered_here():
    assert {"sim", "sim-canopen", "sim-serial", "canopen", "serial"} <= set(device_names())
    assert set(device_names()) - set(SIMULATED) <= set(HARDWARE)


@pytest.mark.parametrize("name", SIMULATED)
def test_simulated_backend_keeps_the_contract(name, request):
    if name == "avr-sim":
        request.getfixturevalue("avr_toolchain")  # tests/conftest.py
    with open_device(name, Rig()) as dev:
        assert isinstance(dev, Device)
        desc = dev.describe()
        assert isinstance(desc, DeviceDescription) and desc.sample_time_s > 0
        assert isinstance(dev, StatusReporting)
        assert dev.status() == DeviceStatus("disabled", None, dev.status().link)
        dev.enable(timeout=2.0)
        assert dev.status().state == "enabled"
        first = dev.read(timeout=2.0)  # the loop's order: read, then command
        dev.command(0.0)
        if isinstance(dev, RawReading):  # optional: the same sample as read(), as a tuple
            seq, t, x, flags = dev.read_raw(timeout=2.0)
            assert seq > first.seq and t > first.t_s and isinstance(flags, int)
            dev.command(0.0)
        s = dev.read(timeout=2.0)
        assert s.seq > first.seq and s.t_s > first.t_s
        dev.command(0.0)
        dev.disable(timeout=2.0)
        assert dev.status().state == "disabled"
    assert dev.status().state == "closed"
    dev.close()  # idempotent


@pytest.mark.parametrize("name", sorted(HARDWARE))
def test_hardware_backend_without_hardware_fails_in_one_line(name):
    with pytest.raises(LabbenchError) as info:
        open_device(name, rig_from_dict(HARDWARE[name]))
    assert "\n" not in str(info.value)
