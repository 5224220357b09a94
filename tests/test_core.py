"""Shared core types: parameter validation, rig files, effective impedances, CLI helpers."""
import json
import math

import numpy as np
import pytest

from labbench.cli import main
from labbench.jsonutil import json_safe
from labbench.registry import open_device
from labbench.model.effective import effective_impedances, measured_wb_star, measured_ws_star
from labbench.errors import UserError
from labbench.rig import load_rig, rig_from_dict
from labbench.model.ve import Plant, VirtualEnvironment


def test_ve_zeroes_unused_gains_and_checks_delay():
    ve = VirtualEnvironment("damper", K=50, B=1, w0=125, td=0.003)
    assert ve.K == 0 and ve.B == 1
    assert ve.delay_samples == 3
    assert ve.delay == pytest.approx(0.0035)
    assert ve.filter_pole == pytest.approx(math.exp(-0.125))
    assert VirtualEnvironment("spring", K=5, B=3).B == 0
    assert VirtualEnvironment.from_dict(ve.as_dict()) == ve
    with pytest.raises(UserError, match="whole number"):
        VirtualEnvironment("spring", K=1, td=0.0015).delay_samples


@pytest.mark.parametrize(
    "kwargs",
    [dict(kind="wall"), dict(K=-1), dict(w0=0), dict(T=0), dict(td=-0.001), dict(K=float("nan"))],
)
def test_ve_rejects_bad_values(kwargs):
    with pytest.raises(UserError):
        VirtualEnvironment(**kwargs)


def test_plant_rejects_nonpositive_mass():
    with pytest.raises(UserError, match="mass"):
        Plant(m=0, b=0.1)
    with pytest.raises(UserError):
        Plant(m=0.1, b=-1)


def test_effective_impedances_of_a_pure_spring_and_mass():
    w = np.logspace(0, 2, 20)
    K, m, b = 50.0, 0.1, 0.3
    spring = effective_impedances(w, K / (1j * w))  # Z = K/s
    np.testing.assert_allclose(spring.ES, K)
    np.testing.assert_allclose(spring.ED, 0, atol=1e-12)
    assert np.all(spring.EIF == 0)  # phase exactly -90 deg: border of EIF, whose value is then 0
    mass = effective_impedances(w, m * 1j * w + b)
    np.testing.assert_allclose(mass.EM, m)
    np.testing.assert_allclose(mass.ED, b)


def test_jerk_feedback_region_uses_unwrapped_phase():
    w = np.array([1.0, 2.0, 4.0])
    # Z = -c (1j w)^2 / (1j w)... use Z = -J w^2 * (phase 180 deg): pure negative real part.
    J = 0.5
    Z = -J * w**2 + 0j
    eff = effective_impedances(w, Z)
    np.testing.assert_allclose(eff.EJF, J)
    np.testing.assert_allclose(eff.ED, -J * w**2)


def test_bandwidth_readers_interpolate_crossings():
    w = np.linspace(1, 400, 4000)
    ES = 50 * (1 - (w / 23.0) ** 2)
    assert measured_ws_star(w, ES) == pytest.approx(23.0, rel=1e-3)
    ED = 0.1 + 1.0 / (1 + (w / 125.0) ** 2)  # falls from 1.1 to 0.1; half-way at w = 125
    assert measured_wb_star(w, ED, 0.1) == pytest.approx(125.0, rel=1e-2)
    assert measured_wb_star(w, np.full_like(w, 0.1), 0.1) is None
    assert measured_ws_star(w, -np.abs(ES) - 1) is None


def test_rig_file_validation(tmp_path):
    good = tmp_path / "rig.toml"
    good.write_text('[rig]\nname = "bench A"\nlever_arm_m = 0.05\ncounts_per_rev = 2000\n'
                    'position_limits_m = [-0.02, 0.03]\n[sim]\nm = 0.2\n')
    rig = load_rig(good)
    assert rig.name == "bench A"
    assert rig.metres_per_count == pytest.approx(2 * math.pi * 0.05 / 2000)
    assert rig.position_limits_m == (-0.02, 0.03)
    assert rig.section("sim") == {"m": 0.2}
    with pytest.raises(UserError, match="lever_arm_m"):
        rig_from_dict({"rig": {"lever_arm_m": -1}})
    with pytest.raises(UserError, match="unknown field"):
        rig_from_dict({"rig": {"lever_arm": 1}})
    with pytest.raises(UserError, match="position_limits_m"):
        rig_from_dict({"rig": {"position_limits_m": [1, 0]}})
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_rig(bad)
    with pytest.raises(UserError, match="not found"):
        load_rig(tmp_path / "missing.toml")


def test_unknown_device_is_a_user_error():
    with pytest.raises(UserError, match="unknown device"):
        open_device("phantom", load_rig(None))


def test_json_safe_is_strict_json():
    out = json_safe({"a": np.array([1.0, np.nan, np.inf]), "b": np.float64(2), "c": np.bool_(True)})
    assert json.loads(json.dumps(out, allow_nan=False)) == {"a": [1.0, None, None], "b": 2.0, "c": True}


def test_cli_usage_error_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0]


def test_closed_pipe_is_not_a_traceback():
    """`labbench ... | head` closes stdout early: exit quietly, no traceback."""
    import subprocess
    import sys

    w = ",".join(str(i / 3) for i in range(1, 8000))  # below Nyquist (3142 rad/s at 1 kHz)
    proc = subprocess.Popen(
        [sys.executable, "-m", "labbench.cli", "theory", "--ve", "spring", "--m", "0.1",
         "--b", "0.1", "--K", "10", "--w", w],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )
    proc.stdout.read(10)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0
    assert "Traceback" not in err and "BrokenPipe" not in err
