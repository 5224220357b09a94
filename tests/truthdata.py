"""Data with known truth for the analysis tests and the benchmark.

The exact open-loop and closed-loop records live in ``labbench.sweep.exact`` (an
analysis sweep feeds them to the estimators); this module adds the test-only ones.
"""
from __future__ import annotations

import numpy as np

from labbench.analysis.dataio import Recording, recording_from_arrays
from labbench.sweep.exact import (  # noqa: F401 - the tests' names for them
    PAPER_B,
    PAPER_M,
    chirp_force,
    chirp_recording,
    closed_loop_recording,
    open_loop,
    with_noise,
    z_truth,
)


def sensor_chirp_recording(n: int = 30000, m: float = PAPER_M, b: float = PAPER_B, fs: float = 1000.0,
                           amp: float = 1.0, f1: float = 20.0, oversample: int = 16) -> Recording:
    """A continuous chirp force (as a force sensor reads it) on m x'' + b x' = f, sampled.

    The force is the chirp at every instant, not held: ``scipy.signal.lsim`` integrates
    the linear ODE exactly for a piecewise-linear input on a grid ``oversample`` times
    finer than the samples (the chirp's curvature between grid points is ~1e-7 of it).
    The record is meant to be read with ``force_hold = sample``.
    """
    from scipy import signal

    t = np.arange(n * oversample) / (fs * oversample)
    f = chirp_force(n * oversample, fs * oversample, f1=f1, amp=amp)
    plant = signal.lti([[0.0, 1.0], [0.0, -b / m]], [[0.0], [1.0 / m]], [[1.0, 0.0]], [[0.0]])
    _, x, _ = signal.lsim(plant, f, t)
    return recording_from_arrays(t[::oversample], f[::oversample], x[::oversample], {"fs": fs},
                                 "<sensor chirp truth>")


def write_csv(rec: Recording, path, extra_meta: dict | None = None) -> None:
    """CSV in the documented layout (# key=value lines, header, rows), columns shuffled."""
    with open(path, "w") as fh:
        fh.writelines(f"# {k}={v}\n" for k, v in {**rec.meta, **(extra_meta or {})}.items())
        fh.write("position,t,force\n")
        np.savetxt(fh, np.column_stack([rec.position, rec.t, rec.force]), delimiter=",", fmt="%.17g")
