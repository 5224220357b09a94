"""``--device avr-sim``: the reference firmware, built for the ATmega328P, on simavr.

The sketch docs/arduino/labbench_encoder.ino is compiled for an Uno
(``labbench.sim_backend.avr_build``) and run by the C harness
(sim_backend/avr/harness.c) inside a simulated mass-damper: the plant's
position drives the encoder pins, the firmware's PWM duty and DIR pin drive the
plant, and the board's UART0 is a pty that the real ``SerialStream`` opens, as
it opens a board on /dev/ttyACM0. So every protocol runs through the firmware
itself, its timing, its integer and float arithmetic and its PWM quantisation.

Pacing is lock-step by default (emulated time waits for the host's answer to
each sample; deterministic and independent of the machine's speed, which is
about real time here), or ``realtime=True`` (emulated time kept to wall time,
as a real board; this machine's emulator may not keep up).

Plant: ``m`` and ``b`` of ``[sim]`` (default the rig's nominal model), ``x0_m``,
``v0_m_s``, ``coulomb_n`` (Coulomb friction, stick/slip as ``--device sim``), and the
truth the rig file may get wrong, ``sign``, ``counts_per_rev``, ``lever_arm_m``
(``labbench.sim_backend.sim_device.true_geometry``) and ``extra_delay_samples`` (an
amplifier that applies each force that many samples late); the amplifier gives
255 / ``PWM_PER_NEWTON`` N at 100 % duty, matched to the sketch's constant. The board adds one sample of delay to everything the
host commands (docs/serial-protocol.md, "Emulated board"); with
``SerialStream.render_on_board`` it renders the VE itself at T / ``RENDER_DIV``.
"""

from __future__ import annotations

import json
import math
import subprocess
import tempfile
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from labbench.errors import DeviceConnectionError, UserError
from labbench.sim_backend import avr_build

CPU_HZ = 16_000_000
PWM_PER_NEWTON = 40.0  # the sketch's default: duty counts (of 255) per newton
VECTOR_TIMER2_COMPA = 7  # ATmega328P interrupt vector of the sketch's tick
RENDER_DIV = 5  # the sketch's default: render ticks per sample (5 kHz at T = 1 ms)
LOCKSTEP_TIMEOUT_S = 3.0  # wall time; generous: this machine is shared and loaded
# The board's own delay, declared to the analyses (labbench.model.device_delay; a rig's
# measured_td_s takes precedence): docs/serial-protocol.md, "Emulated board".
BOARD_DELAY_WHY = ("the reference sketch latches each command at its next tick: one sample "
                   "on everything the host commands")
_PLANT_OPTIONS = ("m", "b", "x0_m", "v0_m_s", "coulomb_n", "extra_delay_samples")
_GEOMETRY_OPTIONS = ("sign", "counts_per_rev", "lever_arm_m")


@dataclass(frozen=True)
class Trace:
    """Events the harness wrote (``--trace``), times in seconds of emulated time."""

    tx: list  # (first_s, last_s, nbytes) per 0x00-terminated run sent by the board
    line: list  # (first_s, last_s, nbytes) per '\n'-terminated run sent by the board
    rx: list  # (first_s, last_s, nbytes) per host frame handed to the UART
    vec: list  # (pending_s, running_s, return_s, count_pending, count_running) per traced ISR
    force: list  # (t_s, newton) from then on
    period_s: float = 0.001

    def sample_ticks(self) -> np.ndarray:
        """``vec`` rows of the ticks that latched samples (row k: sample seq k): the
        ticks on the sample grid (the render ticks between them are off it)."""
        vec = np.array(self.vec)
        phase = (vec[:, 0] - vec[0, 0]) / self.period_s
        return vec[np.abs(phase - np.round(phase)) < 0.05]

    def force_at(self, t) -> np.ndarray:
        """The force the plant felt at times ``t`` [s] (0 before the first change)."""
        times = np.array([at for at, _ in self.force])
        values = np.r_[0.0, [f for _, f in self.force]]
        return values[np.searchsorted(times, np.asarray(t, float), side="right")]

    def plant_positions(self, t, m: float, b: float) -> np.ndarray:
        """Positions at ascending times ``t`` of a mass-damper at rest at 0 under the
        recorded forces, integrated exactly between changes (labbench.model.linear.zoh_matrices),
        independently of the harness's own closed form."""
        from labbench.model.linear import zoh_matrices

        x, t_now, out = np.zeros(2), 0.0, []
        events = iter(self.force + [(math.inf, 0.0)])
        at, f_next = next(events)
        f_now = 0.0
        for t_k in np.asarray(t, float):
            while at <= t_k:
                Ad, Bd = zoh_matrices(m, b, at - t_now)
                x, t_now, f_now = Ad @ x + Bd * f_now, at, f_next
                at, f_next = next(events)
            Ad, Bd = zoh_matrices(m, b, t_k - t_now)
            x, t_now = Ad @ x + Bd * f_now, t_k
            out.append(x[0])
        return np.array(out)

    @classmethod
    def read(cls, path: Path, period_s: float) -> Trace:
        out = {"tx": [], "line": [], "rx": [], "vec": [], "force": []}
        for line in path.read_text().splitlines():
            kind, *fields = line.split()
            if kind in ("tx", "rx", "line"):
                out[kind].append((int(fields[0]) / CPU_HZ, int(fields[1]) / CPU_HZ, int(fields[2])))
            elif kind == "vec":
                t = [int(v) / CPU_HZ for v in fields[:3]]
                out["vec"].append((*t, int(fields[3]), int(fields[4])))
            elif kind == "force":
                out["force"].append((int(fields[0]) / CPU_HZ, float(fields[1])))
        return cls(**out, period_s=period_s)


class AvrBoard:
    """The harness process running one firmware image; ``pty`` is the board's port.

    ``close()`` stops it and returns its statistics (JSON line: emulated and wall
    seconds, edges, final count and plant state, UART bytes, lock-step timeouts).
    """

    def __init__(
        self,
        hex_path: Path,
        *,
        mass_kg: float,
        damping_ns_m: float,
        metres_per_count: float,
        full_scale_n: float,
        x0_m: float = 0.0,
        v0_m_s: float = 0.0,
        coulomb_n: float = 0.0,
        amp_delay_s: float = 0.0,
        baud: int = 500_000,
        realtime: bool = False,
        host_latency_us: float = 30.0,
        trace: bool = False,
        trace_vector: int = VECTOR_TIMER2_COMPA,
        sample_time_s: float = 0.001,
        drive_cps: float | None = None,
        drive_ms: tuple[float, float] = (0.0, 0.0),
        drive_sine: tuple[float, float] = (0.0, 0.0),
        max_ms: float = 0.0,
    ):
        exe = avr_build.build_harness()
        self._dir = Path(tempfile.mkdtemp(prefix="avr-sim-"))
        self.trace_path = self._dir / "trace.txt" if trace else None
        self.sample_time_s = sample_time_s
        args = [
            str(exe), "--hex", str(hex_path), "--mass", repr(mass_kg),
            "--damping", repr(damping_ns_m), "--metres-per-count", repr(metres_per_count),
            "--full-scale-n", repr(full_scale_n), "--x0", repr(x0_m), "--v0", repr(v0_m_s),
            "--coulomb-n", repr(coulomb_n), "--amp-delay-us", repr(amp_delay_s * 1e6),
            "--baud", str(baud), "--host-latency-us", repr(host_latency_us),
            "--lockstep-timeout-ms", repr(LOCKSTEP_TIMEOUT_S * 1e3),
        ]
        if realtime:
            args.append("--realtime")
        if trace:
            args += ["--trace", str(self.trace_path), "--trace-vector", str(trace_vector)]
        if drive_cps is not None:
            args += ["--drive-cps", repr(drive_cps), "--drive-start-ms", repr(drive_ms[0]),
                     "--drive-stop-ms", repr(drive_ms[1]), "--drive-sine-counts",
                     repr(drive_sine[0]), "--drive-sine-hz", repr(drive_sine[1])]
        if max_ms:
            args += ["--max-ms", repr(max_ms)]
        self._stderr = open(self._dir / "stderr.txt", "w+b")
        self._proc = subprocess.Popen(
            args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr
        )
        first = self._proc.stdout.readline().decode().split()
        if len(first) != 2 or first[0] != "pty":
            self._proc.kill()
            raise DeviceConnectionError(f"avr harness did not start: {self._stderr_tail()}")
        self.pty = first[1]
        self.stats: dict | None = None
        self._lock = threading.Lock()

    def start(self) -> None:
        """Release the board from reset (once the host has opened ``pty``)."""
        self._proc.stdin.write(b"g")
        self._proc.stdin.flush()

    def _stderr_tail(self) -> str:
        self._stderr.flush()
        self._stderr.seek(0)
        return self._stderr.read()[-2000:].decode(errors="replace").strip() or "(no output)"

    def close(self, timeout: float = 10.0) -> dict:
        """Stop the emulator (EOF on its stdin) and return its statistics."""
        with self._lock:
            if self.stats is not None:
                return self.stats
            try:  # communicate() closes stdin: the harness stops on its EOF
                out, _ = self._proc.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                out, _ = self._proc.communicate()
            lines = out.decode().strip().splitlines()
            try:
                self.stats = json.loads(lines[-1]) if lines else {}
            except ValueError:
                self.stats = {}
            self.stats["exit_code"] = self._proc.returncode
            self._stderr.close()
            return self.stats

    def trace(self) -> Trace:
        """The events of the run (after ``close``)."""
        return Trace.read(self.trace_path, self.sample_time_s)

    def __del__(self):
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            proc.kill()


def _timer_fits(period_us: int) -> bool:
    """The sketch's Timer2 takes the period (its #if chain): a multiple of 4 us up to 1024,
    8 up to 2048 or 16 up to 4096, whose RENDER_DIV-th part is whole timer counts."""
    for us_per_count in (4, 8, 16):
        if period_us % us_per_count == 0 and period_us // us_per_count <= 256:
            return (period_us // us_per_count) % RENDER_DIV == 0
    return False


def firmware_defines(rig, baud: int) -> dict:
    """The sketch settings that follow the rig: its period and baud rate."""
    period_us = rig.sample_time_s * 1e6
    if abs(period_us - round(period_us)) > 1e-6 or round(period_us) < 100:
        raise UserError(
            f"{rig.source}: avr-sim needs a sample_time_s of whole microseconds >= 100 us, "
            f"got {rig.sample_time_s!r}"
        )
    if not _timer_fits(round(period_us)):
        raise UserError(
            f"{rig.source}: the reference sketch's timer cannot tick every "
            f"{round(period_us)} us: a multiple of 4 us up to 1024, of 8 up to 2048 or of "
            f"16 up to 4096, whose fifth is whole timer counts (e.g. 1000, 2000, 4000)")
    return {"PERIOD_US": f"{round(period_us)}UL", "BAUD": f"{baud}UL"}


def _checked(table: dict) -> dict:
    """The plant's options (``_PLANT_OPTIONS``), validated as ``--device sim`` validates them."""
    from labbench.sim_backend.sim_device import _OPTIONS

    out = {}
    for name in _PLANT_OPTIONS:
        default, ok, what = _OPTIONS[name]
        value = table.get(name, default)
        if not ok(value):
            raise UserError(f"avr-sim option {name} must be {what}, got {value!r}")
        out[name] = float(value)
    return out


def connect_avr_sim(rig, realtime: bool = False, trace: bool = False,
                    trace_vector: int = VECTOR_TIMER2_COMPA, defines: dict | None = None,
                    host_latency_us: float = 30.0, drive_cps: float | None = None,
                    drive_ms: tuple[float, float] = (0.0, 0.0), **options):
    """The real ``SerialStream`` on the emulated board's pty: ``(driver, board)``.

    ``[serial]`` settings apply (port and ``force_command = true`` are forced).
    ``defines`` add sketch settings (``-DNAME=value``). Closing the driver stops
    the emulator.
    """
    import serial

    from labbench.drivers.serial_stream import SerialConfig, SerialStream, synced

    from labbench.sim_backend.sim_device import sim_options, true_geometry

    config = SerialConfig.from_rig(rig, port="avr-sim", force_command=True, format="binary")
    table = _plant_table(rig, options)
    plant = _checked({"m": rig.nominal_mass_kg, "b": rig.nominal_damping_ns_m, **table})
    geo = true_geometry(rig, sim_options(replace(rig, sections={}),
                                         **{k: v for k, v in table.items() if k in _GEOMETRY_OPTIONS}),
                        believed_sign=rig.position_sign * config.direction)
    hex_path = avr_build.build_firmware({**firmware_defines(rig, config.baudrate), **(defines or {})})
    unit = geo.lever_arm_m if config.command_units == "N*m" else 1.0
    board = AvrBoard(
        hex_path,
        mass_kg=plant["m"],
        damping_ns_m=plant["b"],
        # the harness counts one way: a flipped encoder is the same loop as a flipped amplifier
        metres_per_count=geo.metres_per_count,
        full_scale_n=geo.sign * 255.0 / PWM_PER_NEWTON / unit,
        x0_m=plant["x0_m"],
        v0_m_s=plant["v0_m_s"],
        coulomb_n=plant["coulomb_n"],
        amp_delay_s=plant["extra_delay_samples"] * rig.sample_time_s,
        baud=config.baudrate,
        realtime=realtime,
        host_latency_us=host_latency_us,
        trace=trace,
        trace_vector=trace_vector,
        sample_time_s=rig.sample_time_s,
        drive_cps=drive_cps,
        drive_ms=drive_ms,
    )
    try:
        ser = serial.Serial(board.pty, baudrate=config.baudrate, timeout=0)
        board.start()
    except BaseException:
        board.close()
        raise
    T = rig.sample_time_s
    warnings = []
    if rig.measured_td_s is not None and abs(rig.measured_td_s - T) > 0.1 * T:
        warnings.append(f"{rig.source}: [rig] measured_td_s = {rig.measured_td_s:g} s, but the "
                        f"reference sketch on avr-sim adds one sample ({T:g} s) to every "
                        "command: the theory and the pre-check use the rig's value; "
                        "docs/arduino/avr-sim.toml is the rig for this board")
    driver = SerialStream(
        ser, config, rig, on_close=board.close, paced=realtime,
        stale_s=None if realtime else LOCKSTEP_TIMEOUT_S / 2, kind="avr-sim",
        simulated="the reference sketch (docs/arduino/labbench_encoder.ino) on simavr's "
                  "ATmega328P, in a simulated mass-damper",
        device_delay_s=T, device_delay_why=BOARD_DELAY_WHY, warnings=warnings,
    )
    return synced(driver), board


SKETCH_STALE_S = 2.0  # wall time: the emulator of a free-running sketch is not real time


def connect_sketch(rig, sketch: Path, *, defines: dict | None = None, drive_cps: float = 0.0,
                   drive_ms: tuple[float, float] = (0.0, 1e9),
                   drive_sine: tuple[float, float] = (0.0, 0.0), trace: bool = True):
    """A lab's own sketch (docs/arduino/styles/, or any that reads an encoder on pins 2/3
    and prints its count) on the emulated ATmega328P, its encoder moved by a prescribed
    motion (counts: ``drive_cps`` from ``drive_ms[0]`` to ``drive_ms[1]`` plus
    ``drive_sine`` = (amplitude, Hz) over that window), read by the real driver as the
    rig's ``[serial]`` table says (nothing forced). Returns ``(driver, board)`` once the
    driver has the stream. The sketch runs free (no lock-step: it takes no commands), its
    time the emulator's, so the driver does not judge it by wall time (``paced`` False,
    a stale limit of ``SKETCH_STALE_S``)."""
    import serial

    from labbench.drivers.serial_stream import SerialConfig, SerialStream, synced

    config = SerialConfig.from_rig(rig, port="avr-sim")
    hex_path = avr_build.build_firmware(dict(defines or {}), sketch=Path(sketch))
    board = AvrBoard(hex_path, mass_kg=rig.nominal_mass_kg, damping_ns_m=rig.nominal_damping_ns_m,
                     metres_per_count=rig.metres_per_count, full_scale_n=0.0, baud=config.baudrate,
                     trace=trace, sample_time_s=rig.sample_time_s, drive_cps=drive_cps,
                     drive_ms=drive_ms, drive_sine=drive_sine)
    try:
        ser = serial.Serial(board.pty, baudrate=config.baudrate, timeout=0)
        board.start()
    except BaseException:
        board.close()
        raise
    driver = SerialStream(ser, config, rig, on_close=board.close, paced=False,
                          stale_s=SKETCH_STALE_S, kind="avr-sim",
                          simulated=f"{Path(sketch).name} on simavr's ATmega328P, its encoder "
                                    "moved by a prescribed motion")
    return synced(driver), board


def drive_counts(t_s, drive_cps: float, drive_ms: tuple[float, float],
                 drive_sine: tuple[float, float]) -> np.ndarray:
    """The count the harness's prescribed motion shows at emulated times ``t_s`` (its
    drive_position and count_of, for a plant starting at x0 = 0)."""
    t_ms = np.clip(np.asarray(t_s, float) * 1e3, *drive_ms) - drive_ms[0]
    counts = drive_cps * t_ms * 1e-3 + drive_sine[0] * np.sin(2 * np.pi * drive_sine[1] * t_ms * 1e-3)
    return np.floor(counts + 0.5).astype(np.int64)


def _plant_table(rig, options: dict) -> dict:
    table = {**rig.section("sim"), **options}
    table.pop("paced", None)  # how it runs, not the plant (open_avr_sim)
    other = sorted(set(table) - set(_PLANT_OPTIONS) - set(_GEOMETRY_OPTIONS))
    if other:
        raise UserError(
            f"avr-sim option(s) {', '.join(other)} not supported: its plant is a mass-damper "
            f"with {', '.join(_PLANT_OPTIONS + _GEOMETRY_OPTIONS)}"
        )
    return table


def open_avr_sim(rig, realtime: bool | None = None, seed: int | None = None, **options):
    """Device registry factory for ``--device avr-sim`` (``seed`` unused: nothing is random);
    ``realtime`` None: the rig's ``[sim] paced`` (default lock-step)."""
    from labbench.sim_backend.sim_device import paced_by_rig

    return connect_avr_sim(rig, realtime=paced_by_rig(rig, realtime), **options)[0]
