"""Curves of the live plots: lines reduced to pixel columns, paths in view coordinates."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import numpy as np  # noqa: E402
import pyqtgraph as pg  # noqa: E402
import pytest  # noqa: E402

from PySide6 import QtGui  # noqa: E402

from labbench.gui.path_curve import PathCurve, column_spans  # noqa: E402


def _columns_truth(x, y, x0, d0, ppu):
    """Per pixel column: (centre, low, high) of the samples in it and of the line at
    its edges, one column at a time."""
    dev = d0 + (x - x0) * ppu
    out = []
    for c in np.unique(np.floor(dev).astype(int)):
        inside = np.floor(dev).astype(int) == c
        vals = list(y[inside])
        for edge in (c, c + 1):  # where the line between two samples crosses an edge
            k = np.flatnonzero((dev[:-1] < edge) & (dev[1:] >= edge))
            vals += [y[j] + (edge - dev[j]) / (dev[j + 1] - dev[j]) * (y[j + 1] - y[j]) for j in k]
        out.append((x0 + (c + 0.5 - d0) / ppu, min(vals), max(vals)))
    return out


@pytest.mark.parametrize("seed, d0, ppu", [(0, 51.37, 84.3), (1, 0.0, 120.0), (2, 7.9, 33.0)])
def test_column_spans_are_each_columns_samples_and_edge_crossings(seed, d0, ppu):
    rng = np.random.default_rng(seed)
    x = np.arange(-5.0, 0.0, 1e-3)
    ys = np.vstack([rng.standard_normal(x.size), np.cumsum(rng.standard_normal(x.size))])
    xs, spans = column_spans(x, ys, -5.0, d0, ppu)
    for c, y in enumerate(ys):
        truth = _columns_truth(x, y, -5.0, d0, ppu)
        assert xs.size == spans.shape[1] == 2 * len(truth)
        np.testing.assert_allclose(xs[0::2], [t[0] for t in truth], rtol=0, atol=1e-9)
        np.testing.assert_allclose(spans[c, 0::2], [t[1] for t in truth], rtol=0, atol=1e-9)
        np.testing.assert_allclose(spans[c, 1::2], [t[2] for t in truth], rtol=0, atol=1e-9)


def test_column_spans_draw_the_pixels_of_the_full_line(qtbot):
    """Drawn at the screen's resolution, the spans cover what the 5000-point line covers."""
    rng = np.random.default_rng(3)
    x = np.arange(5000) * 1e-3
    lines = {"noise": 100 + 40 * rng.standard_normal(5000),
             "walk": 20 + np.cumsum(rng.standard_normal(5000)) * 0.5}

    def ink(px, py, connect):
        img = QtGui.QImage(440, 260, QtGui.QImage.Format.Format_RGB32)
        img.fill(0xFFFFFFFF)
        p = QtGui.QPainter(img)
        p.setPen(pg.mkPen("k", width=0))
        p.setTransform(QtGui.QTransform.fromScale(84.3, 1.0) * QtGui.QTransform.fromTranslate(10.4, 0))
        p.drawPath(pg.arrayToQPath(px, py, connect=connect))
        p.end()
        a = np.frombuffer(img.constBits(), np.uint8).reshape(260, 440, 4)
        return a[:, :, 0] < 128

    def column_extents(img):
        cols = [np.flatnonzero(img[:, c]) for c in range(img.shape[1])]
        return np.array([(r.min(), r.max()) if r.size else (-99, -99) for r in cols])

    for name, y in lines.items():
        xs, spans = column_spans(x, y[None], 0.0, 10.4, 84.3)
        assert xs.size / 2 <= 0.001 * x.size * 84.3 + 2  # one span a column
        full, drawn = column_extents(ink(x, y, "all")), column_extents(ink(xs, spans[0], "pairs"))
        off = np.abs(full - drawn).max(axis=1)
        assert np.all((full < 0) == (drawn < 0))  # the same columns inked
        # top and bottom of each column as the full line's; for the noise, Qt's 1/64-pixel
        # grid moves the full line itself as much when shifted by 1/100 pixel (measured:
        # 92 % of columns within 1 pixel, 96 % within 5)
        within1, within5 = {"noise": (0.9, 0.94), "walk": (0.95, 1.0)}[name]
        assert np.mean(off <= 1) >= within1 and np.mean(off <= 5) >= within5, name


def test_column_spans_draw_a_gap_in_time_as_the_line_across():
    x = np.concatenate((np.arange(0, 1, 0.01), np.arange(2, 3, 0.01)))
    y = np.arange(x.size, dtype=float)[None]
    xs, spans = column_spans(x, y, 0.0, 0.0, 10.0)
    # 10 + 10 columns with samples, and one segment from the last sample before the gap
    assert xs.size == 2 * 21
    assert (xs[-2], xs[-1], spans[0, -2], spans[0, -1]) == (x[99], x[100], 99.0, 100.0)


def test_path_curve_maps_log_axes_and_breaks_at_gaps(qtbot):
    plot = pg.PlotWidget()  # the curves live in its scene: none outlives the QApplication
    qtbot.addWidget(plot)
    c = PathCurve(pg.mkPen("k", width=1), log=(True, False))
    plot.addItem(c)
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
    plot.addItem(wide)
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


def test_time_traces_redraw_their_columns_when_resized(qtbot):
    """The traces are reduced to the plot's pixel columns: a wider window, more spans."""
    from labbench.gui.buffers import StreamBuffer
    from labbench.gui.live_plots import TimeTraces
    from labbench.records import CHANNELS, DESCRIPTOR, PAGE

    rng = np.random.default_rng(4)
    buf = StreamBuffer()
    buf({"kind": DESCRIPTOR, "sample_time_s": 1e-3})
    data = {name: rng.standard_normal(6000) for name in CHANNELS}
    data["t"] = np.arange(6000) * 1e-3
    buf({"kind": PAGE, "data": data})
    traces = TimeTraces()
    qtbot.addWidget(traces)
    traces.resize(500, 600)
    traces.show()
    qtbot.waitExposed(traces)
    traces.update_from(buf)
    spans = {}
    for width in (500, 900):
        traces.resize(width, 600)
        qtbot.wait(50)  # the layout, then the views' resize events
        vb = traces.plots["position"].getViewBox()
        x, y = traces.curves["position"].getOriginalDataset()
        spans[width] = x.size / 2
        assert abs(spans[width] - vb.width() * traces.devicePixelRatioF()) <= 2
        assert y.max() == data["position"][-5000:].max()
    assert spans[900] > spans[500] + 300
