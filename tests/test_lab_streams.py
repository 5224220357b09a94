"""Streams as labs print them, from a Python board on a pty (the byte streams of
docs/arduino/styles/ and the mismatches simavr cannot show: a pty carries no baud rate):
the rig's ``[serial]`` table declares the layout; each mismatch is one line naming its
cause and the one change (baud, millisecond, count_bits, format and force_command: each
its own); ``labbench devices --rig`` reports what the board sends."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from labbench.cli import main
from labbench.drivers import serial_diagnosis as diagnosis
from labbench.drivers.serial_stream import SerialConfig
from labbench.errors import DeviceError, UserError
from labbench.rig import rig_from_dict
from labbench.sim_backend.arduino_peer import ArduinoPeer, connect_lab_stream
from labbench.sim_backend.plant import PrescribedMotion
from labbench.sim_backend.uart_wire import received

MPC = rig_from_dict({}).metres_per_count
T = 0.01


def lab_rig(T=T, **serial):
    return rig_from_dict({"rig": {"sample_time_s": T},
                          "serial": {"port": "x", "format": "ascii", "baudrate": 115200, **serial}},
                         source="lab.toml")


def sine(amplitude_counts=300.0, hz=1.0):
    return lambda t: amplitude_counts * MPC * math.sin(2 * math.pi * hz * t)


def refusal(host, board, **kw) -> str:
    """The one line the driver gives when ``board`` prints and ``host`` reads (UserError at
    the handshake, or DeviceFault in the first 200 samples)."""
    try:
        drv, _ = connect_lab_stream(host, sine(), prints=board, board_T=board.sample_time_s, **kw)
    except UserError as exc:
        return str(exc)
    try:
        for _ in range(200):
            drv.read(1.0)
    except DeviceError as exc:
        return str(exc)
    finally:
        drv.close()
    raise AssertionError("the stream was read without a word")


# (what the board prints, how the rig reads it, the words, the change named)
MISMATCHES = {
    "baud": (lab_rig(), lab_rig(baudrate=57600),
             {"wire": lambda d: received(d, 115200, 57600)},
             r"never formed a line \(\d+ % not text, .*\): the board sends at another baud rate: "
             r"set \[serial\] baudrate to the rate in the sketch's Serial.begin\(...\) \(now 57600\)"),
    "millisecond": (lab_rig(fields=["millis", "count"]), lab_rig(), {},
                    r"the board's time field counts milliseconds, not microseconds: its lines "
                    r'are 10 apart for a period of 10 ms: set \[serial\] fields = \["millis", '
                    r'"count"\]'),
    "count_bits": (lab_rig(count_bits=16, count_signed=False), lab_rig(), {},
                   r"the count jumped from \d+ to 65\d\d\d between two lines \(a step of 65\d+\): "
                   r"the board's counter is 16 bits wide and wrapped: set \[serial\] count_bits = "
                   r"16 \(count_signed = false: it printed 0..65535\)"),
    "format": (rig_from_dict({"rig": {"sample_time_s": T}, "serial": {"format": "binary"}}),
               lab_rig(), {"banner": b"#labbench encoder v2\r\n"},
               r"the board sends labbench binary frames \(its banner `#labbench encoder v2`\), "
               r'not text lines: set \[serial\] format = "binary"'),
}


@pytest.mark.parametrize("name", sorted(MISMATCHES))
def test_each_mismatch_has_its_own_one_line_message(name):
    board, host, kw, words = MISMATCHES[name]
    message = refusal(host, board, **kw)
    assert "\n" not in message
    assert re.search(words, message), message
    others = [w for n, (_, _, _, w) in MISMATCHES.items() if n != name]
    assert not any(re.search(w, message) for w in others)  # its own message, no other's


def test_force_command_mismatch_is_refused_before_the_board_is_touched(tmp_path, capsys):
    peer = ArduinoPeer(PrescribedMotion(sine(), T), T, MPC, fmt="ascii", realtime=True,
                       boot_noise=False)
    url = peer.open_port()
    rig = tmp_path / "lab.toml"
    rig.write_text(f'[rig]\nsample_time_s = {T}\n[serial]\nport = "{url}"\nformat = "ascii"\n'
                   "force_command = false\n")
    peer.start()
    try:
        for protocol in ("etfe", "commission", "chirp-id"):
            code = main(["run", protocol, "--device", "serial", "--rig", str(rig),
                         "--skip-commissioning", "--out", str(tmp_path / "s")])
            err = capsys.readouterr().err.strip().splitlines()
            assert code == 2 and len(err) == 1
            assert err[0] == (f"labbench run: error: {protocol} drives a force, but {rig}: "
                              "[serial] force_command = false: this board takes no force "
                              "commands (it only streams its count); set force_command = true "
                              "once its sketch reads the 'F' frames of docs/serial-protocol.md")
        assert peer.commands.frames == 0 and peer.commands.garbage_bytes == 0  # never written to
        assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())
    finally:
        peer.close()


def test_on_change_cannot_take_force_commands():
    with pytest.raises(UserError, match="on_change = true cannot take force commands: a board "
                                        "that prints only on change looks the same dead or still"):
        SerialConfig.from_rig(lab_rig(fields=["count"], on_change=True, force_command=True))


@pytest.mark.parametrize("table, words", [
    ({"fields": ["micros", "millis", "count"]}, "at most one time field"),
    ({"fields": ["micros", "position"]}, '"count" once'),
    ({"fields": "count"}, "a list of 1 to 8 distinct names"),
    ({"fields": ["count", "count"]}, "distinct"),
    ({"count_signed": 0}, "count_signed must be true or false"),
    ({"format": "binary", "fields": ["count"]}, 'fields is for text lines \\(format = "ascii"\\)'),
])
def test_bad_stream_declarations_are_one_line(table, words):
    with pytest.raises(UserError, match=words):
        SerialConfig.from_rig(lab_rig(**table))


def test_a_board_without_time_is_numbered_by_the_host_at_its_rate():
    rig = lab_rig(fields=["count", "pwm"])
    drv, peer = connect_lab_stream(rig, sine(), seed=1)
    try:  # not enabled: a Python board on a loaded machine may pause longer than 3 periods
        samples = [drv.read(1.0) for _ in range(60)]
        info = drv.stream_info()
    finally:
        drv.close()
    assert info["time"] == "host: lines numbered at the rig's period"
    assert info["period_s"] == pytest.approx(T, rel=0.1)  # the host's clock, a thread's ticks
    seq = np.array([s.seq for s in samples])
    assert np.all(np.diff(seq) >= 1)  # (before enable a read takes the newest line)
    np.testing.assert_allclose([s.t_s for s in samples], seq * T)
    counts = np.array([round(s.position_m / MPC) for s in samples])
    truth = np.floor(300 * np.sin(2 * np.pi * seq * T) + 0.5)  # the board's count at line seq
    assert np.array_equal(counts, truth)


def test_a_board_at_another_rate_without_time_is_measured_by_the_host_clock():
    message = refusal(lab_rig(T=0.005, fields=["count"]), lab_rig(fields=["count"]))
    m = re.fullmatch(r"the board prints every ([\d.]+) ms \(by the host's clock over \d+ lines\) "
                     r"but the rig's sample_time_s is 5.000 ms: set \[rig\] sample_time_s = "
                     r"([\d.]+) \(the sketch fixes its period\) or change the sketch's period",
                     message)
    assert m and float(m[1]) == pytest.approx(10.0, rel=0.1)  # a Python thread's ticks
    assert float(m[2]) == pytest.approx(float(m[1]) * 1e-3, rel=0.01)


def test_no_steady_rate_is_named_with_the_sketch_line_to_change():
    rng = np.random.default_rng(3)
    steps = rng.uniform(0.2, 2.6, 40) * T * 1e6
    seen = diagnosis.Seen("pty", samples=[(int(t), k, None) for k, t in
                                          enumerate(np.cumsum(steps))])
    message = diagnosis.timing(seen, SerialConfig.from_rig(lab_rig()), T)
    assert message.startswith("the board prints at no steady rate: its lines are ")
    assert "set [serial] on_change = true; else schedule its print on a timer" in message
    # ... and a millis()-scheduled board (9.216 / 10.24 ms steps) is steady enough
    steady = diagnosis.Seen("pty", samples=[(int(t), 0, None) for t in np.cumsum(
        rng.choice([9216, 10240], 40))])
    assert diagnosis.timing(steady, SerialConfig.from_rig(lab_rig()), T) is None


@pytest.mark.parametrize("raw, prev, bits, signed, words", [
    (0, 65535, 32, True, "jumped from 65535 to 0 .* count_bits = 16 \\(count_signed = false"),
    (-32768, 32767, 32, True, "count_bits = 16 \\(count_signed = true"),
    (70000, 69000, 16, False, "beyond 16 bits: its counter is wider: set \\[serial\\] count_bits = 32"),
    (40000, 39999, 16, True, "beyond a signed 16-bit counter: set \\[serial\\] count_signed = false"),
    (-3, -2, 16, False, "beyond a unsigned 16-bit counter: set \\[serial\\] count_signed = true"),
])
def test_count_width_mismatches(raw, prev, bits, signed, words):
    assert re.search(words, diagnosis.count_problem(raw, prev, bits, signed))


@pytest.mark.parametrize("raw, prev, bits, signed", [
    (70000, 30000, 32, True),  # a 32-bit counter's big step, beyond 16 bits
    (-40000, -1000, 32, True),
    (65535, 0, 16, False),  # a real 16-bit wrap, declared
    (-1, 0, 16, True),
    (5, 65535, 16, False),
])
def test_count_width_checks_raise_no_false_alarm(raw, prev, bits, signed):
    assert diagnosis.count_problem(raw, prev, bits, signed) is None


def test_an_untimed_board_whose_banner_comes_again_rebooted():
    from labbench.drivers.serial_stream import Reboot, StreamDecoder

    config = SerialConfig.from_rig(lab_rig(fields=["count"]))
    dec = StreamDecoder(config, T, MPC)
    out = dec.feed(b"encoder ready\r\n5\r\n6\r\n7\r\nencoder ready\r\n0\r\n")
    assert [type(o).__name__ for o in out] == ["Decoded"] * 3 + ["Reboot", "Decoded"]
    assert out[3] == Reboot("board rebooted: its banner came again")
    assert out[4].sample.position_m == 0.0


@pytest.fixture
def lab_board(tmp_path):
    """A free-running board printing ``<millis>,<count>`` on a pty, and a rig file for it."""
    peer = ArduinoPeer(PrescribedMotion(sine(), T), T, MPC, fmt="ascii", realtime=True,
                       boot_noise=False, fields=("millis", "count"))
    url = peer.open_port()
    peer.start()

    def rig(**serial):
        path = tmp_path / "lab.toml"
        lines = "".join(f"{k} = {json.dumps(v)}\n" for k, v in serial.items())
        path.write_text(f'[rig]\nsample_time_s = {T}\n[serial]\nport = "{url}"\n'
                        f'format = "ascii"\n{lines}')
        return str(path)

    yield rig
    peer.close()


def test_devices_opens_the_board_and_says_what_it_sends(lab_board, capsys):
    assert main(["devices", "--rig", lab_board(fields=["millis", "count"])]) == 0
    out = capsys.readouterr().out.split("serial       configured\n")[1].splitlines()
    assert out[0].strip().startswith("port /dev/") and "bytes in" in out[0]
    assert out[1].strip().startswith("first lines: `")
    assert out[2].strip() == 'stream: ascii, fields ["millis", "count"]; time from the board millis'
    assert out[3].strip() == "period: 10 ms (steps 10 to 10 ms over 12 lines)"
    assert out[4].strip().startswith("counts over 1 s: ") and "samples, moving, " in out[4]
    assert out[5].strip() == "ok: the rig's [serial] table reads this board"
    assert main(["devices", "--rig", lab_board(), "--json"]) == 2
    row = next(r for r in json.loads(capsys.readouterr().out)["devices"] if r["device"] == "serial")
    assert row["answer"]["refused"].startswith("the board's time field counts milliseconds")
    assert row["answer"]["bytes"] > 0 and row["answer"]["first_lines"]


def test_devices_on_a_silent_port_is_no_answer(tmp_path, capsys):
    import os

    master, slave = os.openpty()
    try:
        rig = tmp_path / "lab.toml"
        rig.write_text(f'[rig]\nsample_time_s = {T}\n[serial]\nport = "{os.ttyname(slave)}"\n'
                       'format = "ascii"\nsync_timeout_s = 0.3\n')
        assert main(["devices", "--rig", str(rig)]) == 1
        out = capsys.readouterr().out
        assert "refused: no bytes from /dev/" in out and "the board is silent" in out
    finally:
        os.close(master)
        os.close(slave)


def test_millisecond_stamps_at_a_thousandth_of_the_period_are_told_by_the_host_clock():
    """The trap the old message set (its advice, sample_time_s = 1e-5, made the lines fit):
    the board's time advances a thousandth as fast as the host's clock."""
    message = refusal(lab_rig(T=1e-5), lab_rig(fields=["millis", "count"]))
    assert re.fullmatch(r"the board's time field counts milliseconds, not microseconds: it "
                        r"advances 0.00\d+ s per second of the host's clock: set \[serial\] "
                        r'fields = \["millis", "count"\] \(and \[rig\] sample_time_s to the '
                        r"sketch's period\)", message), message


def test_the_wire_at_the_right_rate_is_the_bytes_and_at_another_is_no_text():
    data = b"".join(b"%d,%d\r\n" % (1000 * k, 3 * k) for k in range(300))
    assert received(data, 115200, 115200) == data
    assert received(data, 57600, 57601) == data  # within a bit's half over 10 bits
    for rate in (9600, 57600, 230400):
        wrong = received(data, 115200, rate)
        assert diagnosis.noise_share(wrong) > diagnosis.NOISE_SHARE
        assert wrong.count(b"\n") < data.count(b"\n") / 4
    # a stop bit read low is a framing error, read as 0x00 (Linux raw tty)
    fast = received(b"UUUU", 9600, 115200)  # 12 receiver bits in the start bit alone
    assert fast[0] == 0 and fast.count(0) >= 4 and b"U" not in fast
