"""Simulated backends say what they are (issue 31, defect 6): simulated and whether paced in
``describe()``, paced as the rig would on request, one E-STOP state, link counters from the
connection, the status figures from one timing summary, avr-sim's own delay declared."""
import pytest

from labbench.device import ESTOP_STATE
from labbench.errors import DeviceFault
from labbench.registry import make_protocol, open_device
from labbench.rig import Rig, rig_from_dict
from labbench.runner import run
from labbench.loop.timing import status_figures
from can_fixtures import no_bus_left_open  # noqa: F401

BACKENDS = ["sim", "sim-canopen", "sim-serial", "avr-sim"]


@pytest.fixture
def backend(request):
    """The backend's name; avr-sim needs the firmware toolchain (conftest)."""
    if request.param == "avr-sim":
        request.getfixturevalue("avr_toolchain")
    return request.param


def rig_with(sim: dict | None = None, **tables) -> Rig:
    return rig_from_dict({**({"sim": sim} if sim is not None else {}), **tables},
                         source="test-rig")


@pytest.mark.parametrize("backend", BACKENDS, indirect=True)
def test_every_simulated_backend_says_it_is_simulated_and_how_it_is_paced(backend):
    with open_device(backend, rig_with()) as d:
        desc = d.describe()
        assert desc.simulated and not desc.paced  # lock-step by default
        assert "simulated" in desc.label() or "simavr" in desc.label()
        assert "lock-step" in desc.label()
        if backend == "sim-canopen":
            assert desc.name == "simulated CiA 402 drive, node 1" and desc.kind == "canopen"
            assert "in a thread of this process" in desc.simulated
    with open_device(backend, rig_with({"paced": True})) as d:
        assert d.describe().paced and "paced at the sample time" in d.describe().label()
    with open_device(backend, rig_with({"paced": True}), realtime=False) as d:
        assert not d.describe().paced  # an explicit choice wins over the rig


def test_hardware_drivers_say_nothing_of_simulation():
    from labbench.drivers.canopen_config import CanopenConfig
    from labbench.drivers.canopen_drive import CanopenDrive

    desc = CanopenDrive(Rig(), CanopenConfig()).describe()
    assert desc.simulated == "" and desc.name == "CiA 402 drive, node 1"
    assert desc.label() == "CiA 402 drive, node 1 (canopen)"


@pytest.mark.parametrize("backend", ["sim-canopen", "sim-serial"], indirect=True)
def test_a_paced_simulated_run_keeps_the_wall_clock(backend):
    """Paced by the rig, a 1 s run keeps the wall clock (a lock-step run takes a tenth of it)
    and its timing is judged as a paced loop's. Over CANopen the host paces the drive (its
    SYNCs): the loop's own wall time is the run's. A serial board paces itself from the
    moment it is opened, and samples it made while the run started wait queued and are read
    at once (0.36 s of them in a whole-suite run on CI, where the simulated board shares the
    process with the loop): the run cannot end before its 100 samples were made, 0.99 s after
    the device was open. At 100 Hz: the board's 2.5-period stale limit outlasts a loaded
    machine's stalls (at 1 kHz it does not, which is why lock-step is the default)."""
    import time

    rig = rig_with({"paced": True}, rig={"sample_time_s": 0.01},
                   canopen={"stale_periods": 20}, safety={"watchdog_s": 2.0})
    protocol = make_protocol("etfe", duration_s=1.0, seed=3, sample_time_s=0.01)
    device = open_device(backend, rig)
    opened = time.perf_counter()
    result = run(device, protocol, [], rig=rig)
    since_open = time.perf_counter() - opened
    # ran to its end: 100 samples are too few for the ETFE's analysis (failed, cause analysis)
    assert result.status == "success" or result.cause == "analysis", result.reason
    t = result.timing
    assert t["paced"] and t["periods"] == 99
    assert (t["wall_s"] if backend == "sim-canopen" else since_open) >= 0.95, (since_open, t)
    figures = status_figures(t)
    assert figures["paced"] and figures["overruns"] is not None
    assert figures["rate_text"].startswith("paced at 100 Hz")


@pytest.mark.parametrize("backend", BACKENDS, indirect=True)
def test_one_e_stop_state_everywhere(backend):
    with open_device(backend, rig_with()) as d:
        d.emergency_stop()
        assert d.status().state == ESTOP_STATE


@pytest.mark.parametrize("backend", ["sim-serial", "avr-sim"], indirect=True)
def test_link_counters_start_at_the_connection(backend):
    """A fault-free link shows no bad frame or garbage after connecting (what the board
    sent before its stream, boot text and a partial frame, is the handshake's); garbage
    after it is counted."""
    with open_device(backend, rig_with()) as d:
        counters = d.status().link
        assert counters["bad_frames"] == 0 and counters["garbage_bytes"] == 0, counters
        assert counters["crc_errors"] == 0
        assert sum(d.describe().details["handshake"].values()) > 0  # boot text, samples


def test_garbage_after_the_connection_is_counted():
    from labbench.sim_backend.arduino_peer import Fault, connect_sim_serial

    d, peer = connect_sim_serial(Rig(), faults=[Fault("garbage", at=40, n=30)], seed=1)
    with d:
        d.enable()
        with pytest.raises(DeviceFault, match="serial link error"):
            for _ in range(60):
                d.read(1.0)
                d.command(0.0)
        link = d.status().link
        assert link["garbage_bytes"] == 30 and link["bad_frames"] == 1, link


def test_status_figures_from_one_summary_paced_and_lock_step():
    lock_step = {"T_s": 0.001, "paced": False, "periods": 9999, "wall_s": 5.0,
                 "p50_s": 0.0005, "p99_s": 0.00165, "max_s": 0.02, "overruns": 0}
    f = status_figures(lock_step)
    assert f["speed"] == pytest.approx(2.0, rel=1e-3) and f["overruns"] is None
    assert f["rate_text"] == "lock-step (unpaced): 2x real time"
    paced = {"T_s": 0.001, "paced": True, "n": 5000, "wall_s": 5.001, "p99_s": 0.00102,
             "overruns": 3, "max_s": 0.004, "worst_t_s": 1.2}
    f = status_figures(paced)
    assert f["rate_text"] == "paced at 1000 Hz: 1000 samples/s" and f["overruns"] == 3
    assert f["worst_t_s"] == 1.2
    assert status_figures({})["samples_per_s"] is None


def test_live_snapshots_carry_what_the_status_figures_need():
    snaps = []
    run(open_device("sim", Rig()), make_protocol("etfe", duration_s=1.0, seed=3), [],
        rig=Rig(), live_timing=snaps.append)
    assert snaps and {"n", "wall_s", "T_s", "paced", "overruns", "max_s"} <= set(snaps[-1])
    assert status_figures(snaps[-1])["samples_per_s"] > 0


@pytest.mark.usefixtures("avr_toolchain")
def test_avr_sim_declares_its_own_sample_of_delay():
    """The reference sketch latches each command at its next tick: the default rig's theory
    matches with no rig file; a rig that says otherwise is told which file fits."""
    from labbench.model import device_delay

    with open_device("avr-sim", Rig()) as d:
        desc = d.describe()
        assert desc.device_delay_s == pytest.approx(0.001)
        assert device_delay.resolve(Rig(), desc).origin == "device"
        assert "warnings" not in desc.details
    wrong = rig_from_dict({"rig": {"measured_td_s": 0.0}}, source="wrong.toml")
    with open_device("avr-sim", wrong) as d:
        (warning,) = d.describe().details["warnings"]
        assert "docs/arduino/avr-sim.toml" in warning and "wrong.toml" in warning


@pytest.mark.usefixtures("avr_toolchain")
def test_avr_sim_is_simulated_for_the_commissioning_gate(tmp_path):
    """The runner takes the description's word: avr-sim on an uncommissioned rig renders a
    spring (hardware would be refused)."""
    rig = Rig()
    result = run(open_device("avr-sim", rig), make_protocol("etfe", duration_s=1.0, seed=3),
                 [], rig=rig)
    assert result.status == "success", result.reason
