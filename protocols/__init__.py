"""Protocols: plain validated config data plus steps (see protocols/base.py).

``make_protocol(name, **options)`` builds one by name; ``precheck(protocol, plant)``
checks its VE against the exact sampled stability boundary before enabling.
"""
from __future__ import annotations

from labbench.errors import UserError
from protocols.base import Protocol, Segment, SegmentOutcome, nominal_plant, precheck
from protocols.chirp_id import ChirpId, ChirpIdConfig
from protocols.stability_probe import StabilityConfig, StabilityProbe
from protocols.white_noise import EtfeConfig, WhiteNoiseEtfe

# name -> (protocol class, config class)
PROTOCOLS = {
    "chirp-id": (ChirpId, ChirpIdConfig),
    "etfe": (WhiteNoiseEtfe, EtfeConfig),
    "stability": (StabilityProbe, StabilityConfig),
}


def make_protocol(name: str, **options) -> Protocol:
    """A protocol by name with validated options (one UserError per bad field)."""
    try:
        cls, config_cls = PROTOCOLS[name]
    except KeyError:
        raise UserError(f"unknown protocol {name!r}; choose one of {', '.join(PROTOCOLS)}") from None
    return cls(config_cls.from_options(name, options))


__all__ = ["PROTOCOLS", "Protocol", "Segment", "SegmentOutcome", "make_protocol", "nominal_plant",
           "precheck"]
