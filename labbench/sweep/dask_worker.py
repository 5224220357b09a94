"""What a local sweep worker does when it starts (a Dask preload: ``dask_setup``).

Ctrl-C and a closed terminal signal the whole foreground process group: the
sweep's own worker processes too. Left to their default they die at once, with
a traceback each and the points they were computing lost to the stop that the
driver (``labbench sweep``) makes in order anyway: cancel, write the rows it
has, shut the workers down. So they ignore those signals; SIGTERM stays theirs
(how their nanny ends them).
"""
from __future__ import annotations

import signal


def dask_setup(worker) -> None:  # noqa: ARG001 - the preload interface
    from labbench.platform.signals import ending_signals

    for s in ending_signals():
        if s != signal.SIGTERM:
            signal.signal(s, signal.SIG_IGN)
