"""Sessions recorded on the default simulated rig, for the tests of what reads them."""
from labbench.registry import make_protocol
from labbench.rig import Rig
from labbench.runner import run
from labbench.sessions.session_format import SessionWriter
from labbench.sim_backend.sim_device import open_sim

TRUTH = {"m": 0.094, "b": 0.10}  # the default simulated rig


def record_session(directory, name, **options):
    """Run protocol ``name`` on the simulator (seed 1) into ``directory``: (path, RunResult)."""
    rig = Rig()
    with SessionWriter(directory) as w:
        result = run(open_sim(rig, seed=1), make_protocol(name, **options), [w], rig=rig)
    assert result.status == "success", result.reason
    return w.path, result
