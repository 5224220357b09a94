"""labbench: a lab bench for impedance-type haptic displays.

``labbench.load(path)`` opens a session or CSV for analysis (``labbench.session_api``);
it is imported on first use so that ``import labbench`` stays light.
"""
import os as _os

__version__ = "0.1.0"
__all__ = ["load", "__version__"]

# Imported from the repository's own folder (``python -m labbench`` in its root, whatever is
# installed): the plug-in folders beside this one (drivers/, protocols/, gui/, sim_backend/)
# are mapped into ``labbench`` only by an install (pyproject.toml ``package-dir``), so this
# package looks for its subpackages there too.
_root = _os.path.dirname(__path__[0])
if (not _os.path.isdir(_os.path.join(__path__[0], "protocols"))
        and _os.path.isfile(_os.path.join(_root, "protocols", "__init__.py"))):
    __path__.append(_root)
del _root


def __getattr__(name):
    if name == "load":
        from labbench.session_api import load

        return load
    raise AttributeError(f"module 'labbench' has no attribute {name!r}")
