"""The command line's own conventions: --version, python -m, -v/-q logging, one-line errors for
missing optional packages, --port for serial devices and the serial port listing."""
from __future__ import annotations

import json
import logging
import subprocess
import sys

import pytest
from serial.tools import list_ports
from serial.tools.list_ports_common import ListPortInfo

import labbench
from labbench.cli import main


def test_version_and_python_m():
    out = subprocess.run([sys.executable, "-m", "labbench", "--version"], capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == f"labbench {labbench.__version__}"
    helped = subprocess.run([sys.executable, "-m", "labbench", "--help"], capture_output=True,
                            text=True, check=True)
    assert "-v, --verbose" in helped.stdout and "report" in helped.stdout


@pytest.fixture
def restore_logging():
    root, libs = logging.getLogger(), [logging.getLogger(n) for n in ("canopen", "can")]
    saved = (root.level, list(root.handlers), [lg.level for lg in libs])
    yield
    root.setLevel(saved[0])
    root.handlers[:] = saved[1]
    for lg, level in zip(libs, saved[2]):
        lg.setLevel(level)


THEORY = ["theory", "--ve", "spring", "--m", "0.094", "--b", "0.1", "--K", "50", "--json"]


@pytest.mark.parametrize("flags, canopen_info, labbench_warning", [
    ([], False, True), (["-v"], True, True), (["-q"], False, False)])
def test_verbosity_reaches_canopen_logging(capsys, restore_logging, flags, canopen_info,
                                           labbench_warning):
    assert main([*flags, *THEORY]) == 0
    capsys.readouterr()
    logging.getLogger("canopen.sdo.client").info("SDO upload 0x1018")
    logging.getLogger("labbench.drivers.canopen_drive").warning("heartbeat late")
    err = capsys.readouterr().err
    assert ("canopen.sdo.client: INFO: SDO upload 0x1018" in err) == canopen_info
    assert ("labbench.drivers.canopen_drive: WARNING: heartbeat late" in err) == labbench_warning


def test_vv_is_debug(restore_logging):
    assert main(["-vv", *THEORY]) == 0
    assert logging.getLogger("canopen").getEffectiveLevel() == logging.DEBUG


def test_missing_optional_package_is_one_line(monkeypatch, capsys, tmp_path):
    import labbench.cli.report as report_cli

    def needs_pandas(args):
        import pandas  # noqa: F401 - hidden below

    monkeypatch.setitem(sys.modules, "pandas", None)  # as if not installed
    monkeypatch.setattr(report_cli, "run", needs_pandas)
    assert main(["report", "x.lbsession", "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == ("labbench report: error: labbench report needs pandas: "
                   "pip install 'haptic-labbench[pandas]'\n")


def test_port_goes_to_the_serial_driver(tmp_path, capsys):
    port = str(tmp_path / "ttyACM9")  # no such device: the driver must name it
    assert main(["run", "chirp-id", "--device", "serial", "--port", port, "--out",
                 str(tmp_path / "s"), "--duration-s", "20"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot open serial port {port}" in err[0]
    assert main(["run", "chirp-id", "--device", "sim", "--port", port]) == 2
    assert "--port is for --device serial" in capsys.readouterr().err


def test_devices_serial_lists_what_pyserial_sees(capsys, monkeypatch):
    assert main(["devices", "--serial", "--json"]) == 0
    listed = [p["device"] for p in json.loads(capsys.readouterr().out)["serial_ports"]]
    assert listed == sorted(p.device for p in list_ports.comports())
    usb = ListPortInfo("/dev/ttyACM0", skip_link_detection=True)
    usb.description, usb.manufacturer, usb.vid, usb.pid, usb.serial_number = (
        "Arduino Uno", "Arduino (www.arduino.cc)", 0x2341, 0x0043, "85736323838351F0D1C1")
    monkeypatch.setattr(list_ports, "comports", lambda: [usb])
    assert main(["devices", "--serial"]) == 0
    assert capsys.readouterr().out == ("/dev/ttyACM0     Arduino Uno (Arduino (www.arduino.cc), "
                                       "USB 2341:0043, serial 85736323838351F0D1C1)\n")


def test_version_imports_no_numerical_library():
    # --version is answered before the subcommands register (they import numpy, scipy);
    # its time is measured in bench/bench_startup.py, not here
    code = ("import sys; from labbench.cli import main; main(['--version']); "
            "print(sorted(m for m in ('numpy', 'scipy', 'labbench.analysis') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == [f"labbench {labbench.__version__}", "[]"]
