"""The live ETFE: block-by-block sums equal the batch Welch estimator exactly; on an exact
known closed loop it meets the default estimator's accuracy targets and agrees with the
final estimate within its band; its memory does not grow with the record."""
from __future__ import annotations

import numpy as np
import pytest

from labbench.analysis.dataio import recording_from_arrays
from labbench.analysis.etfe import etfe
from labbench.analysis.etfe_live import LEVELS, LiveEtfe
from labbench.errors import UserError
from labbench.model.ve import VirtualEnvironment

from truthdata import closed_loop_recording, z_truth

SPRING_DAMPER = VirtualEnvironment("spring-damper", K=50.0, B=1.0, w0=125.0)


@pytest.fixture(scope="module")
def rec():
    return closed_loop_recording(SPRING_DAMPER)


def feed(live, rec, sizes, budget=None):
    i, k = 0, 0
    while i < len(rec.force):
        n = sizes[k % len(sizes)]
        live.add(rec.force[i:i + n], rec.position[i:i + n], budget=budget)
        i, k = i + n, k + 1
    return live


def test_block_by_block_is_the_batch_welch_estimate(rec):
    """Segments of 2^14 summed as 100-sample blocks arrive = etfe's h1-welch on the record."""
    batch = etfe(rec, estimator="h1-welch")
    for sizes, budget in (([100], None), ([37, 1000, 3], 2**14), ([len(rec.force)], None)):
        live = feed(LiveEtfe(rec.fs, levels=(2**14,)), rec, sizes, budget)
        live.add([], [])  # a budgeted feed catches up
        w, Z = live.raw(live.levels[0])
        assert live.levels[0].count == 2 * len(rec.force) // 2**14 - 1
        np.testing.assert_allclose(w, batch.w, rtol=1e-12)
        np.testing.assert_allclose(Z, batch.Z, rtol=1e-9)


def test_accurate_and_within_its_band_of_truth_and_of_the_final_estimate(rec):
    live = feed(LiveEtfe(rec.fs), rec, [100], budget=2**15)
    est = live.estimate()
    assert live.level().n == max(LEVELS)
    sel = (est.w >= 2.0) & (est.w <= 100.0)
    assert sel.sum() >= 50
    Zt = z_truth(SPRING_DAMPER, est.w[sel])
    err = np.abs(est.Z[sel] - Zt) / np.abs(Zt)
    assert np.median(err) <= 0.01 and err.max() <= 0.05  # the default estimator's targets
    final = etfe(rec)
    Zf = np.interp(est.w[sel], final.w, final.Z.real) + 1j * np.interp(est.w[sel], final.w,
                                                                        final.Z.imag)
    band = est.Z_err[sel]
    assert np.median(band / np.abs(est.Z[sel])) < 0.05  # not vacuous
    # a 95 % band on ~67 frequencies; the final estimate has errors of its own
    assert (np.abs(est.Z[sel] - Zt) <= band).mean() >= 0.8
    assert (np.abs(est.Z[sel] - Zf) <= band).mean() >= 0.8


def test_early_estimate_and_constant_memory(rec):
    live = LiveEtfe(rec.fs)
    live.add(rec.force[:1000], rec.position[:1000])
    assert live.estimate() is None  # not one 2 s segment yet
    live.add(rec.force[1000:3000], rec.position[1000:3000])
    assert live.level().n == min(LEVELS) and live.estimate() is not None
    feed(live, recording_from_arrays(rec.t[3000:], rec.force[3000:], rec.position[3000:],
                                     rec.meta), [500], budget=2**15)
    assert len(live._f) == 2 * max(LEVELS) and live.n == len(rec.force)


def test_mismatched_blocks_are_refused():
    with pytest.raises(UserError):
        LiveEtfe(1000.0).add(np.zeros(3), np.zeros(4))
