"""pyqtgraph's plots and their menus kept for the life of the process.

A ViewBox's right-click menu is a parentless QMenu whose QWidgetActions own
default widgets (a PlotItem's "Plot Options" holds its widgets on the item's
Python side). When Python's cyclic GC freed such a menu, PySide 6 (6.11 here)
destroyed the action's widget after its children's wrappers were gone and
segfaulted in Shiboken::BindingManager::releaseWrapper (caught under gdb in a GUI
test run: dict_dealloc -> ~QMenu -> ~QWidgetAction -> ~QWidget). pyqtgraph #2497
and #2520 are the leak and crash behind it; mantidimaging keeps its views alive
the same way. Kept wrappers are never freed; plots are made once per window, so
what is kept is small.
"""
from __future__ import annotations

import pyqtgraph as pg

_KEPT: list = []


def keep_plots(*views: pg.GraphicsView) -> None:
    """Hold every PlotItem and ViewBox (and so their menus) in the scenes of ``views``;
    call once their plots are made."""
    for view in views:
        _KEPT.extend(item for item in view.scene().items() if isinstance(item, (pg.ViewBox, pg.PlotItem)))
