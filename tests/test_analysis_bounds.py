"""Memory of the analyses bounded by construction (issue 30): no frequencies x frequencies
arrays where the errors are independent, whatever the record's length."""
import tracemalloc

import numpy as np

from labbench.analysis import rendered


def test_rendered_fit_of_independent_errors_keeps_no_n_by_n_matrix():
    # a paper estimate of an 1800 s record puts ~10 000 bins in the low band: as n x n
    # covariance matrices its rendered K and B took 2.1 GB; the diagonal gives the same numbers
    n = 5000
    w = np.linspace(2.0, 40.0, n)
    Z = 50.0 / (1j * w) + 1.1 + 0.094j * w
    se = 0.01 * np.abs(Z)
    dense = rendered.fit(w, Z, se, np.eye(n))  # the same errors, their correlation given
    tracemalloc.start()
    try:
        lean = rendered.fit(w, Z, se)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, peak  # one 5000^2 matrix is 200 MB
    for k in ("K", "B"):
        assert getattr(lean, k) == getattr(dense, k)
        assert np.allclose(getattr(lean, f"{k}_ci95"), getattr(dense, f"{k}_ci95"), rtol=1e-12)
