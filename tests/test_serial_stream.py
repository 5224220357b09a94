"""Serial driver: unwrapping, configuration, decoding; the driver against the simulated board."""

import math
import os
import threading

import numpy as np
import pytest
import serial

from labbench.drivers import framing
from labbench.drivers.serial_stream import (
    FLAG_LINK_ERRORS,
    FLAG_LOST,
    Decoded,
    Reboot,
    SerialConfig,
    SerialStream,
    StreamDecoder,
    open_serial,
)
from labbench.drivers.unwrap import Unwrapper, wrap_delta
from labbench.device import Device, DeviceFault
from labbench.errors import DeviceConnectionError, UserError
from labbench.rig import Rig, rig_from_dict
from labbench.platform.serial_peer import SocketTransport
from labbench.sim_backend import arduino_peer
from labbench.sim_backend.arduino_peer import ArduinoPeer, connect_sim_serial, default_plant
from labbench.sim_backend.plant import MassDamperPlant


@pytest.fixture(autouse=True)
def no_board_left_running():
    """Fail any test that leaves a simulated board thread running (driver not closed)."""
    yield
    alive = [t for t in threading.enumerate() if t.name == "arduino-peer" and t.is_alive()]
    assert not alive, "a simulated board was left running: close its driver"


def make_rig(**serial_table):
    return rig_from_dict(
        {"rig": {"sample_time_s": 0.001}, "serial": serial_table}, source="test.toml"
    )


# -- unwrapping -------------------------------------------------------------------------
@pytest.mark.parametrize("bits", [16, 32])
def test_unwrapper_recovers_a_random_walk_across_many_wraps(bits):
    rng = np.random.default_rng(bits)
    half = 1 << (bits - 1)
    steps = rng.integers(-half + 1, half, 2000)  # any step smaller than half a range
    truth = np.cumsum(steps) - 3 * half
    u = Unwrapper(bits, signed=True)
    got = [u.update(int(v) & ((1 << bits) - 1)) for v in truth]
    start = int(truth[0]) & ((1 << bits) - 1)
    offset = (start - (1 << bits) if start >= half else start) - int(truth[0])
    assert np.array_equal(np.array(got) - offset, truth)
    assert abs(truth[-1] - truth[0]) > 4 * half  # it really wrapped


def test_unwrapper_signed_start_and_sign_extended_input():
    u = Unwrapper(16, signed=True)
    assert u.update(0xFFFE) == -2
    assert u.update(-1) == -1  # a sign-extended 16-bit value is the same counter reading
    assert u.update(1) == 1
    t = Unwrapper(32, signed=False)
    assert t.update(2**32 - 500) == 2**32 - 500
    assert t.update(500) == 2**32 + 500  # micros() wrapped after 71.6 min
    assert t.update(400) == 2**32 + 400 and t.last_step == -100


def test_wrap_delta():
    assert wrap_delta(3, 65533, 16) == 6
    assert wrap_delta(65533, 3, 16) == -6


# -- configuration ----------------------------------------------------------------------
@pytest.mark.parametrize(
    "field, value",
    [
        ("baudrate", 0),
        ("baudrate", 9600.5),
        ("format", "hex"),
        ("count_bits", 24),
        ("direction", 2),
        ("force_command", "yes"),
        ("command_units", "Nm"),
        ("stale_periods", 4),
        ("stale_periods", 0.5),
        ("tolerate_drops", -1),
        ("tolerate_link_errors", 1),
        ("sync_timeout_s", 0),
        ("port", 3),
        ("count_bits", True),
    ],
)
def test_config_rejects_each_bad_field_in_one_line(field, value):
    with pytest.raises(UserError) as exc:
        SerialConfig.from_rig(make_rig(**{field: value}))
    msg = str(exc.value)
    assert f"[serial] {field}" in msg and "test.toml" in msg and "\n" not in msg


def test_config_unknown_field_and_defaults():
    with pytest.raises(UserError, match="unknown field.*baud_rate"):
        SerialConfig.from_rig(make_rig(baud_rate=9600))
    c = SerialConfig.from_rig(make_rig(port="/dev/ttyACM0", format="ascii", count_bits=16))
    assert (c.port, c.format, c.count_bits, c.stale_periods) == ("/dev/ttyACM0", "ascii", 16, 2.5)


def test_open_serial_user_errors():
    with pytest.raises(UserError, match="port is not set"):
        open_serial(make_rig())
    with pytest.raises(DeviceConnectionError, match="cannot open serial port /nonexistent/tty"):
        open_serial(make_rig(port="/nonexistent/tty"))


def _open_error(port: str) -> str:
    with pytest.raises(DeviceConnectionError) as exc:
        open_serial(make_rig(port=port))
    return str(exc.value)


@pytest.mark.parametrize("os_error, why, check", [
    (None, "it is not there", "labbench devices --serial"),
    (PermissionError(13, "Permission denied"), "permission denied", "usermod -aG"),
    (OSError(16, "Device or resource busy"), "it is busy", "close it and connect again"),
    ("file", "it is not a serial device", "choose the board's port"),
    ("dir", "it is not a serial device", "choose the board's port"),
])
def test_a_port_that_will_not_open_says_once_which_why_and_what_to_check(
        tmp_path, monkeypatch, os_error, why, check):
    """pyserial's own exception (its errno and its nested '[Errno N] ...' text) from what the
    OS says. Permission and busy cannot happen to root (these tests' user on CI), so the OS's
    refusal is injected where pyserial opens the path; a missing path, a plain file and a
    folder are real."""
    port = str(tmp_path / "ttyACM3")
    if os_error == "file":
        open(port, "w").close()
    elif os_error == "dir":
        os.mkdir(port)
    elif os_error is not None:
        real_open = os.open

        def refusing(path, *args, **kw):
            if path == port:
                raise type(os_error)(os_error.errno, os_error.strerror, path)
            return real_open(path, *args, **kw)

        open(port, "w").close()
        monkeypatch.setattr(os, "open", refusing)
    msg = _open_error(port)
    assert msg.startswith(f"cannot open serial port {port}: {why}"), msg
    assert check in msg and "\n" not in msg
    assert msg.count(port) == 1 and "Errno" not in msg  # the port and the reason once


def test_open_serial_on_a_silent_port_gives_a_clear_error():
    master, slave = os.openpty()
    try:
        rig = make_rig(port=os.ttyname(slave), sync_timeout_s=0.2)
        with pytest.raises(UserError, match="no bytes from .* within 0.2 s: the board is silent"):
            open_serial(rig)
    finally:
        os.close(master)
        os.close(slave)


# -- decoding ---------------------------------------------------------------------------
def _decoder(**table):
    rig = make_rig(**table)
    return StreamDecoder(SerialConfig.from_rig(rig), rig.sample_time_s, rig.metres_per_count), rig


def test_decoder_binary_gaps_reboot_and_calibration():
    dec, rig = _decoder(direction=-1)
    frames = [framing.encode_sample(k, 1000 * k, 10 * k) for k in (65534, 65535, 65536, 65539)]
    out = dec.feed(
        b"".join(frames) + b"\x17junk\x00" + framing.encode_sample(65540, 65_540_000, 655_400)
    )
    samples = [d.sample for d in out]
    assert [s.seq for s in samples] == [65534, 65535, 65536, 65539, 65540]
    assert [d.lost for d in out] == [0, 0, 0, 2, 0]
    assert samples[3].flags & FLAG_LOST and samples[4].flags & FLAG_LINK_ERRORS
    assert samples[1].position_m == pytest.approx(-10 * 65535 * rig.metres_per_count)
    assert dec.counters()["lost"] == 2 and dec.counters()["bad_frames"] == 1
    out = dec.feed(framing.encode_sample(0, 300_000, 0))
    assert isinstance(out[0], Reboot) and "time went from" in out[0].reason
    assert isinstance(out[1], Decoded) and out[1].lost == 0 and dec.reboots == 1


def test_decoder_ascii_seq_from_time_and_wraps():
    dec, rig = _decoder(format="ascii", count_bits=16)
    lines = b"4294966296,32767\r\n4294967296,-32768\r\n".replace(b"4294967296", b"0")
    lines += b"1000,-32767\r\n4000,-32766\r\n4000,-1\r\n"
    out = dec.feed(lines)
    assert [d.sample.seq for d in out] == [4294966, 4294967, 4294968, 4294971]
    assert [d.lost for d in out] == [0, 0, 0, 2]
    counts = [round(d.sample.position_m / rig.metres_per_count) for d in out]
    assert counts == [32767, 32768, 32769, 32770]  # the 16-bit counter unwrapped
    assert dec.duplicates == 1


# -- the driver against the simulated board -----------------------------------------------
def _oracle_positions(rig, forces, delay=0):
    plant = default_plant(rig)
    applied = [0.0] * delay + list(forces)
    xs = []
    for f in applied[: len(forces)]:
        xs.append(plant.position)
        plant.step(f)
    return np.round(np.array(xs) / rig.metres_per_count) * rig.metres_per_count


def _run(drv, forces, timeout=1.0):
    out = []
    for f in forces:
        out.append(drv.read(timeout))
        drv.command(f)
    return out


@pytest.mark.parametrize("transport", ["pty", "socket"])
@pytest.mark.parametrize("fmt", ["binary", "ascii"])
@pytest.mark.parametrize("delay", [0, 1])
def test_lockstep_positions_equal_the_exact_sampled_plant(fmt, delay, transport, monkeypatch):
    """Through a pty and through the local socket used where there is none (Windows)."""
    if transport == "socket":
        monkeypatch.setattr(arduino_peer, "open_transport", lambda warn=None: SocketTransport())
    rig = make_rig(format=fmt)
    forces = 0.4 * np.sin(np.arange(400) * 0.05) + 0.1
    drv, peer = connect_sim_serial(rig, seed=3, delay_samples=delay)
    with drv:
        assert isinstance(drv, Device)
        drv.enable(1.0)
        x0 = peer.plant.position
        assert x0 == 0.0  # nothing applied before enable
        samples = _run(drv, forces)
        d = drv.describe()
    assert peer.url.startswith("socket://") == (transport == "socket")
    seqs = np.array([s.seq for s in samples])
    assert np.array_equal(np.diff(seqs), np.ones(len(seqs) - 1))
    assert np.allclose(np.diff([s.t_s for s in samples]), rig.sample_time_s, atol=1e-6)
    # The sync samples before enable ran under zero force, so the oracle starts at rest too.
    pos = np.array([s.position_m for s in samples])
    assert np.array_equal(pos, _oracle_positions(rig, forces, delay))
    assert d.kind == "sim-serial" and d.force_limit_n == rig.force_limit_n
    assert d.details["counters"]["lost"] == 0 and d.details["counters"]["reboots"] == 0
    assert peer.error is None


def test_command_units_newton_metre_reach_the_plant_as_newton():
    rig = make_rig(command_units="N*m")
    drv, peer = connect_sim_serial(rig, seed=1)
    with drv:
        drv.enable(1.0)
        _run(drv, [0.25] * 20)
        drv.read(1.0)
        # The board received torque 0.25 * lever_arm and converted it back.
        assert list(peer.applied)[-20:] == pytest.approx([0.25] * 20, rel=1e-6)


def test_force_is_clamped_to_the_rig_limit_and_zero_when_disabled():
    rig = make_rig()
    drv, _peer = connect_sim_serial(rig, seed=1)
    with drv:
        drv.command(1.0)  # not enabled: held at zero
        assert drv.commanded_force_n == 0.0
        drv.enable(1.0)
        drv.read(1.0)
        drv.command(100.0)
        assert drv.commanded_force_n == rig.force_limit_n
        drv.read(1.0)
        drv.disable()
        assert drv.commanded_force_n == 0.0


def test_sixteen_bit_counter_and_micros_wrap_through_the_pty():
    rig = make_rig(count_bits=16, format="binary")
    # Start 0.3 s before micros() wraps and 20 counts below the 16-bit limit.
    drv, _peer = connect_sim_serial(rig, seed=2, t0_us=2**32 - 300_000, count0=32_740)
    forces = [2.0] * 300 + [-2.0] * 300
    with drv:
        drv.enable(1.0)
        samples = _run(drv, forces)
    t = np.array([s.t_s for s in samples])
    assert np.allclose(np.diff(t), rig.sample_time_s, atol=1e-6)
    assert t[0] < 2**32 * 1e-6 < t[-1]  # crossed the micros() wrap
    counts = np.array([round(s.position_m / rig.metres_per_count) for s in samples])
    assert (
        np.all(np.abs(np.diff(counts)) < 1000) and counts.max() > 32_767
    )  # crossed the counter wrap
    expect = _oracle_positions(rig, forces) / rig.metres_per_count + counts[0]
    assert np.array_equal(counts, expect)


def test_boot_noise_on_open_is_skipped_and_counted_as_the_handshakes():
    """The board's boot text and banner are the handshake's (``describe().details``), not
    link errors: the link counters start at the connection."""
    rig = make_rig(format="ascii")
    drv, _peer = connect_sim_serial(rig, seed=7)
    with drv:
        h = drv.describe().details["handshake"]
        assert h["garbage_bytes"] > 0 or h["malformed_lines"] > 0
        assert h["comment_lines"] == 1  # the banner
        c = drv.counters()
        assert c["garbage_bytes"] == c["malformed_lines"] == c["comment_lines"] == 0
        drv.enable(1.0)
        assert drv.read(1.0).flags == 0


def test_loop_url_port_carries_board_bytes_to_the_driver():
    rig = make_rig()
    port = serial.serial_for_url("loop://", baudrate=1_000_000, timeout=0)
    plant = MassDamperPlant(0.1, 0.2, rig.sample_time_s, x0=0.01, v0=0.05)
    peer = ArduinoPeer(plant, rig.sample_time_s, rig.metres_per_count, seed=1)
    peer.attach_loop(port)
    # The test is the board's clock here: a generous stale limit.
    drv = SerialStream(port, SerialConfig.from_rig(rig), rig, stale_s=1.0)
    with drv:
        peer.boot()
        peer.emit(5)
        drv.wait_for_stream(0.5)
        drv.enable(0.5)
        xs = []
        for _ in range(50):
            xs.append(plant.position)
            peer.emit(1, force_n=0.0)
            assert drv.read(0.5).position_m == pytest.approx(
                round(xs[-1] / rig.metres_per_count) * rig.metres_per_count
            )
    assert xs[-1] > xs[0] + 0.001  # the plant was moving, so positions really changed


def test_realtime_board_applies_each_answer_one_period_later():
    # 20 ms periods: a free-running board in Python on this shared machine keeps time there.
    rig = rig_from_dict({"rig": {"sample_time_s": 0.02}, "serial": {"stale_periods": 3}})
    drv, peer = connect_sim_serial(rig, realtime=True, seed=4)
    sent = {}
    with drv:
        drv.enable(1.0)
        for i in range(60):
            s = drv.read(0.2)
            sent[s.seq] = 0.01 * (i + 1)
            drv.command(sent[s.seq])
    # peer.applied[k] is the force of period k since boot; the answer to k lands in k+1.
    hits = [
        peer.applied[k + 1] == pytest.approx(f)
        for k, f in sent.items()
        if k + 1 < len(peer.applied)
    ]
    assert len(hits) > 50 and sum(hits) >= 0.8 * len(hits)


def test_close_is_idempotent_and_stops_the_board():
    drv, peer = connect_sim_serial(make_rig(), seed=1)
    drv.close()
    drv.close()
    assert not peer._thread.is_alive()
    with pytest.raises(DeviceFault, match="closed"):
        drv.read(0.1)


@pytest.mark.parametrize("fmt", ["binary", "ascii"])
def test_period_mismatch_is_a_user_error(fmt):
    rig = rig_from_dict(
        {"rig": {"sample_time_s": 0.002}, "serial": {"format": fmt}}, source="r.toml"
    )
    plant = default_plant(rig)
    peer = ArduinoPeer(plant, 0.001, rig.metres_per_count, fmt=fmt, seed=1)  # board at 1 kHz
    url = peer.open_port()
    drv = SerialStream(
        serial.serial_for_url(url, timeout=0),
        SerialConfig.from_rig(rig, force_command=True),
        rig,
        on_close=peer.close,
    )
    peer.start()
    expected = {
        "binary": "every 1.000 ms but the rig's sample_time_s is 2.000 ms",
        "ascii": r"every 1.000 ms \(by its micros field\) but the rig's sample_time_s is "
                 r"2.000 ms: set \[rig\] sample_time_s = 0.001",
    }[fmt]
    with drv, pytest.raises(UserError, match=expected):
        drv.wait_for_stream(1.0)
    assert math.isfinite(plant.position)


# -- the same protocol on the plain simulator and through the serial driver ------------------
def run_protocol(device, rig, **options):
    from labbench.registry import open_device
    from labbench.records import concat_pages
    from labbench.runner import run
    from labbench.registry import make_protocol

    stream = []
    result = run(
        open_device(device, rig), make_protocol("etfe", **options), [stream.append], rig=rig
    )
    return result, concat_pages(stream), stream


def etfe_rig(**serial_table):
    # Lock-step board time is virtual: a generous loop watchdog keeps this loaded
    # shared machine's scheduling hiccups from reading as a frozen loop.
    return rig_from_dict(
        {"sim": {"quantize": True}, "serial": serial_table, "safety": {"watchdog_s": 2.0}},
        source="etfe-rig",
    )


@pytest.mark.parametrize("fmt", ["binary", "ascii"])
def test_short_etfe_record_matches_the_plain_simulator_count_for_count(monkeypatch, fmt):
    """5 s of the white-noise protocol through the runner on ``sim`` and ``sim-serial``.

    Both quantise position to encoder counts; the serial path also carries the
    force as float32 (relative error 6e-8), which can move a position across a
    count boundary, never by more than one count. Each such flip feeds back as
    a one-count kick of the VE force (below), so about 1 % of samples differ
    (measured 0.99 % over 30 s); the bound leaves room for that.
    """
    from labbench.protocols.white_noise import WhiteNoiseEtfe

    monkeypatch.setattr(WhiteNoiseEtfe, "analyze", lambda self, data, meta: {})
    rig = etfe_rig(format=fmt)
    (r_sim, a, _), (r_ser, b, stream) = (
        run_protocol(d, rig, duration_s=5.0, seed=11) for d in ("sim", "sim-serial")
    )
    assert r_sim.status == r_ser.status == "success", (r_sim.reason, r_ser.reason)
    assert stream[0]["device"]["kind"] == "sim-serial"
    assert np.array_equal(a["excitation"], b["excitation"]) and len(b["t"]) == 5000
    assert np.all(np.diff(b["seq"]) == 1) and np.allclose(np.diff(b["t"]), rig.sample_time_s)
    dc = np.round((a["position"] - b["position"]) / rig.metres_per_count)
    assert np.abs(dc).max() <= 1
    assert np.mean(dc != 0) < 0.03
    assert np.std(a["position"]) / rig.metres_per_count > 20  # the handle really moved
    # One count q of position moves the VE force by at most K q + 2 B (1 - a) q / T
    # (spring term, plus the filtered backward difference over two steps).
    q, T = rig.metres_per_count, rig.sample_time_s
    one_count_n = 50.0 * q + 2 * 1.0 * (1 - math.exp(-125.0 * T)) * q / T
    assert np.max(np.abs(a["command"] - b["command"])) <= one_count_n * 1.001


def cli_etfe(tmp_path, device, duration_s):
    """``labbench run etfe --device DEVICE`` with a rig file; (JSON output, session channels)."""
    import contextlib
    import io
    import json

    from labbench.cli import main
    from labbench.sessions.session_content import load_session

    rig_file = tmp_path / "rig.toml"
    rig_file.write_text("[sim]\nquantize = true\n[safety]\nwatchdog_s = 2.0\n")
    out = io.StringIO()
    argv = [
        "run",
        "etfe",
        "--device",
        device,
        "--rig",
        str(rig_file),
        "--seed",
        "11",
        "--duration-s",
        str(duration_s),
        "--out",
        str(tmp_path / device),
        "--json",
    ]
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    result = json.loads(out.getvalue())
    _, _, data, events, stop, problem = load_session(result["session"])
    assert problem is None and stop["status"] == "success"
    return result, data, events


def compare_etfe_runs(tmp_path, duration_s):
    """The same ETFE from the CLI on ``sim`` and ``sim-serial``: records and estimates."""
    (ra, a, _), (rb, b, events) = (cli_etfe(tmp_path, d, duration_s) for d in ("sim", "sim-serial"))
    n = round(duration_s / 0.001)
    assert len(b["t"]) == n and np.all(np.diff(b["seq"]) == 1)
    assert not [e for e in events if e["name"] in ("device_fault", "watchdog", "seq_gap")]
    q = Rig().metres_per_count
    dc = np.round((a["position"] - b["position"]) / q)
    assert np.abs(dc).max() <= 1 and np.mean(dc != 0) < 0.03  # see the short runner test
    za, zb = (
        np.asarray(r["results"]["etfe"]["Z_re"]) + 1j * np.asarray(r["results"]["etfe"]["Z_im"])
        for r in (ra, rb)
    )
    w = np.asarray(ra["results"]["etfe"]["w"])
    band = (w >= 2.0) & (w <= 100.0)
    # "Within noise": the two estimates are closer to each other than either is to
    # the exact theory, whose residual here is the encoder quantisation noise
    # (measured: 10 s, 3e-6 vs 2e-3; 120 s, 2.9e-5 vs 1.3e-4).
    between = float(np.median(np.abs(za[band] - zb[band]) / np.abs(za[band])))
    scatter = ra["results"]["deviation_vs_sampled"]["median_rel"]
    assert between < 0.5 * scatter, (between, scatter)
    other = rb["results"]["deviation_vs_sampled"]["median_rel"]
    assert other == pytest.approx(scatter, rel=0.2)
    return between, scatter


def test_cli_etfe_through_the_serial_driver_matches_the_plain_simulator(tmp_path):
    compare_etfe_runs(tmp_path, 10.0)


@pytest.mark.slow
def test_cli_full_etfe_through_the_serial_driver_matches_the_plain_simulator(tmp_path):
    """The whole 2-minute white-noise ETFE protocol, analysis included, on both devices."""
    compare_etfe_runs(tmp_path, 120.0)
