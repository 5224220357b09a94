"""Commissioning (issue 20): simulated rigs whose rig file is wrong in one known way."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from labbench.errors import UserError
from labbench.registry import open_device
from labbench.rig import Rig, rig_from_dict


def _push(dev, force_n: float, n: int) -> np.ndarray:
    """Positions under a constant force for n samples (from rest)."""
    dev.enable()
    xs = []
    for _ in range(n):
        xs.append(dev.read(2.0).position_m)
        dev.command(force_n)
    dev.command(0.0)
    return np.array(xs)


@pytest.mark.parametrize("backend", ["sim", "sim-canopen"])
def test_sim_truth_that_lies(backend):
    """[sim] sign / counts_per_rev / lever_arm_m: what the rig believes is reported, the
    truth is moved. x_reported = sign (C_true / C_file) (r_file / r_true) x_true, and the
    handle feels F r_file / r_true (torque through the lever arm)."""
    rig = Rig()
    n, F = 200, 0.1
    with open_device(backend, rig) as dev:
        true = _push(dev, F, n)
    assert true[-1] > 0  # a true rig: positive force, positive position
    for sim, gain in (({"sign": -1}, -1.0), ({"counts_per_rev": rig.counts_per_rev / 2}, 0.5),
                      ({"lever_arm_m": rig.lever_arm_m / 1.25}, 1.25 ** 2)):
        with open_device(backend, replace(rig, sections={"sim": sim})) as dev:
            x = _push(dev, F, n)
        # the mass-damper is linear: the lie is a gain on the whole response (counts: rounding)
        np.testing.assert_allclose(x[1:], gain * true[1:], rtol=1e-6, atol=2 * rig.metres_per_count)


def test_rig_position_sign_undoes_a_flipped_encoder():
    rig = rig_from_dict({"rig": {"position_sign": -1}, "sim": {"sign": 1}})
    assert rig.position_per_count == -rig.metres_per_count
    with open_device("sim", rig) as dev:
        x = _push(dev, 0.5, 50)
    assert x[-1] < 0  # the file says the encoder is flipped, the truth is not: flipped
    with open_device("sim", rig_from_dict({"rig": {"position_sign": -1}, "sim": {"sign": -1}})) as dev:
        assert _push(dev, 0.5, 50)[-1] > 0
    for bad in (0, 2, 1.0, True, "1"):
        with pytest.raises(UserError, match="position_sign"):
            rig_from_dict({"rig": {"position_sign": bad}})
    with pytest.raises(UserError, match="sign"):
        open_device("sim", rig_from_dict({"sim": {"sign": 0}}))
