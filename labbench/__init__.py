"""labbench: a lab bench for impedance-type haptic displays."""
__version__ = "0.1.0"
