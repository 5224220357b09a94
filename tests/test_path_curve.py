"""Curves of the live plots: peak reduction to the screen, paths in view coordinates."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import numpy as np  # noqa: E402
import pyqtgraph as pg  # noqa: E402
import pytest  # noqa: E402

from labbench.gui.path_curve import PathCurve, reduce_to_columns  # noqa: E402


@pytest.mark.parametrize("n, group, first", [(5000, 11, 0), (5000, 11, 123_457), (997, 4, 3), (40, 1, 5)])
def test_reduction_keeps_first_lowest_highest_last_of_absolute_sample_groups(n, group, first):
    rng = np.random.default_rng(n + group + first)
    x = (first + np.arange(n)) * 1e-3
    ys = rng.standard_normal((3, n))
    xr, yr = reduce_to_columns(x, ys, group, first)
    assert xr.shape == yr.shape and xr.shape[0] == 3
    if group == 1:
        np.testing.assert_array_equal(xr[1], x)
        assert yr is ys
        return
    # truth, one group at a time: samples k with the same (first + k) // group
    ids = (first + np.arange(n)) // group
    for c in range(3):
        kept = []
        for g in np.unique(ids):
            k = np.flatnonzero(ids == g)
            y = ys[c, k]
            kept += sorted({k[0], k[np.argmin(y)], k[np.argmax(y)], k[-1]})
        # duplicates (a first sample that is also the lowest) are repeated points: drop them
        pts = list(dict.fromkeys(zip(xr[c].tolist(), yr[c].tolist())))
        assert pts == [(x[k], ys[c, k]) for k in kept]


def test_reduction_of_a_scrolled_window_repeats_the_groups_it_shares():
    """Groups follow the samples as the window scrolls: no flicker of the drawn shape."""
    rng = np.random.default_rng(1)
    y = rng.standard_normal(6000)
    x = np.arange(6000) * 1e-3
    _, a = reduce_to_columns(x[:5000], y[None, :5000], 11, 0)
    _, b = reduce_to_columns(x[37:5037], y[None, 37:5037], 11, 37)
    # the whole groups of 11 from sample 44 to 4993: 4 points each
    np.testing.assert_array_equal(a[0, 4 * 4:4 * 454], b[0, 4 * 1:4 * 451])


def test_path_curve_maps_log_axes_and_breaks_at_gaps(qtbot):
    c = PathCurve(pg.mkPen("k", width=1), log=(True, False))
    w = np.array([1.0, 10.0, 100.0, 1000.0])
    y = np.array([1.0, np.nan, 3.0, 4.0])
    c.setData(w, y, connect="finite")
    assert c.getOriginalDataset()[0] is not None and c.pen().widthF() == 0  # drawn 1 px
    path = c.path()
    lines = [(path.elementAt(i - 1), path.elementAt(i)) for i in range(1, path.elementCount())
             if path.elementAt(i).isLineTo()]
    drawn = [((a.x, a.y), (b.x, b.y)) for a, b in lines if (a.x, a.y) != (b.x, b.y)]
    assert drawn == [((2.0, 3.0), (3.0, 4.0))]  # log10 of w; no line into or out of the NaN
    wide = PathCurve(pg.mkPen("k", width=3))
    wide.setData([0.0, 1.0, 2.0], [0.0, 1.0, 0.0])
    # wide pens: one subpath per segment (as pyqtgraph draws them), width kept
    assert wide.path().elementCount() == 4 and wide.pen().widthF() == 3
    wide.setData([], [])
    assert wide.path().isEmpty()


def test_a_view_fits_its_range_to_a_wide_curves_data(qtbot):
    """Auto range uses the data's bounds, not the stroked outline (3 data units wide)."""
    plot = pg.PlotWidget()
    qtbot.addWidget(plot)
    c = PathCurve(pg.mkPen("k", width=3), log=(True, True))
    plot.addItem(c)
    c.setData([10.0, 100.0, 1000.0], [1.0, 10.0, 3.0])
    assert c.dataBounds(0) == (1.0, 3.0) and c.dataBounds(1) == (0.0, 1.0)
    plot.getViewBox().autoRange(padding=0)
    (x0, x1), (y0, y1) = plot.getViewBox().viewRange()
    assert 0.9 < x0 <= 1.0 and 3.0 <= x1 < 3.1 and -0.1 < y0 <= 0.0 and 1.0 <= y1 < 1.1
