"""labbench: a lab bench for impedance-type haptic displays.

``labbench.load(path)`` opens a session or CSV for analysis (``labbench.session_api``);
it is imported on first use so that ``import labbench`` stays light.
"""
__version__ = "0.1.0"
__all__ = ["load", "__version__"]


def __getattr__(name):
    if name == "load":
        from labbench.session_api import load

        return load
    raise AttributeError(f"module 'labbench' has no attribute {name!r}")
