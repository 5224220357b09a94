"""The device's Coulomb friction: one number (with its interval), resolved once per run,
read by every analysis that compares a measurement with the theory.

What it is: the level Fc [N] of ``Fc sign(v)`` at the handle, which the linear theory
leaves out and ``labbench.model.friction`` puts back as the damper it acts as at the
run's own excitation.

Where it comes from, first found wins (``resolve``):

1. ``given``: the protocol's ``plant_coulomb_n`` (with ``plant_coulomb_ci95``): typed
   in, or the chirp-ID's, which ``labbench run --plant-from last-id``, the demo and the
   window pass with its m and b (the start record's ``plant_from`` then names that
   session: ``labbench.readout.wording`` says "chirp-ID ...");
2. ``device``: a simulated device's own friction (its description's
   ``details["coulomb_n"]``, the simulator's ``[sim] coulomb_n``): the truth;
3. ``none``: not known; the analysis estimates it from the record itself
   (``labbench.analysis.friction``, origin ``record`` in its results).

A run's start record carries ``friction = {"n", "ci95", "source", "origin"}`` and the
analysis metadata ``coulomb_n`` (``coulomb_ci95`` as ``lo,hi``, ``coulomb_source``),
which a CSV may give too.
"""
from __future__ import annotations

from dataclasses import dataclass

from labbench.errors import UserError
from labbench.scales import is_number

ORIGINS = ("given", "device", "record", "none")
MAX_COULOMB_N = 1000.0  # as the rig's force limit: no handle holds more
META_KEY, META_CI, META_SOURCE, META_ORIGIN = "coulomb_n", "coulomb_ci95", "coulomb_source", "coulomb_origin"


@dataclass(frozen=True)
class DeviceFriction:
    """Fc [N] (None: not known) with its 95 % interval (None: exact, as given), where it
    came from in words (``source``) and by kind (``origin``, one of ``ORIGINS``)."""

    n: float | None = None
    ci95: tuple[float, float] | None = None
    source: str = "none known: estimated from the record (a chirp-ID measures it)"
    origin: str = "none"

    @property
    def known(self) -> bool:
        return self.n is not None

    @property
    def interval(self) -> tuple[float, float]:
        """The 95 % interval, (n, n) when none was given."""
        return self.ci95 if self.ci95 is not None else (self.n, self.n)

    def as_dict(self) -> dict:
        return {"n": self.n, "ci95": None if self.ci95 is None else list(self.ci95),
                "source": self.source, "origin": self.origin}

    def as_meta(self) -> dict:
        """The analysis metadata keys (module doc); none when not known."""
        if self.n is None:
            return {}
        meta = {META_KEY: self.n, META_SOURCE: self.source, META_ORIGIN: self.origin}
        if self.ci95 is not None:
            meta[META_CI] = f"{self.ci95[0]!r},{self.ci95[1]!r}"
        return meta


NONE = DeviceFriction()


def checked(n, what: str = "Coulomb friction") -> float:
    """``n`` as a float in [0, MAX_COULOMB_N] N, or one UserError naming ``what``."""
    ok = is_number(n)
    if not ok or not 0.0 <= n <= MAX_COULOMB_N:
        raise UserError(f"{what} must be a number of newtons in [0, {MAX_COULOMB_N:g}], got {n!r}")
    return float(n)


def checked_ci(ci, n: float, what: str = "Coulomb friction's 95 % interval") -> tuple[float, float] | None:
    """A [lo, hi] interval holding ``n``, or None for None. An identification's interval of a
    small Fc may reach below zero: kept as stated."""
    if ci is None:
        return None
    ok = isinstance(ci, (list, tuple)) and len(ci) == 2 and all(
        is_number(x) for x in ci)
    if not ok:
        raise UserError(f"{what} must be two finite numbers lo, hi [N], got {ci!r}")
    lo, hi = float(ci[0]), float(ci[1])
    if not (-MAX_COULOMB_N <= lo <= n <= hi <= MAX_COULOMB_N):
        raise UserError(f"{what} [{lo:g}, {hi:g}] N must hold the value {n:g} N within "
                        f"+-{MAX_COULOMB_N:g} N")
    return lo, hi


def given(n: float, ci95=None, source: str = "given in the run's settings") -> DeviceFriction:
    value = checked(n)
    return DeviceFriction(value, checked_ci(ci95, value), source, "given")


def resolve(protocol=None, description=None) -> DeviceFriction:
    """The run's friction (module doc for the order). ``protocol``: its config's
    ``plant_coulomb_n`` / ``plant_coulomb_ci95``; ``description``: the device's
    ``DeviceDescription`` (a simulator states its own)."""
    config = getattr(protocol, "config", None)
    n = getattr(config, "plant_coulomb_n", None)
    if n is not None:
        return given(n, getattr(config, "plant_coulomb_ci95", None))
    details = getattr(description, "details", None) or {}
    own = details.get("coulomb_n")
    if getattr(description, "simulated", "") and own is not None:
        return DeviceFriction(checked(own, "the simulator's coulomb_n"), None,
                              f"the simulator's [sim] coulomb_n, {description.kind}", "device")
    return NONE


def from_dict(d) -> DeviceFriction | None:
    """A recorded ``friction`` dict back (None when it is not one: a file is not trusted)."""
    if not isinstance(d, dict):
        return None
    origin = d.get("origin") if d.get("origin") in ORIGINS else "given"
    source = d.get("source") if isinstance(d.get("source"), str) else "recorded"
    if d.get("n") is None:
        return DeviceFriction(None, None, source, "none") if origin == "none" else None
    try:
        n = checked(d.get("n"))
        return DeviceFriction(n, checked_ci(d.get("ci95"), n), source, origin)
    except UserError:
        return None


def from_start(start: dict) -> DeviceFriction:
    """The friction a session's start record says its run used; NONE when it says none."""
    got = from_dict(start.get("friction")) if isinstance(start, dict) else None
    return got if got is not None else NONE


def from_meta(meta: dict) -> DeviceFriction:
    """The friction of analysis metadata (module doc); NONE when absent. A bad value is one
    UserError naming the key."""
    if not isinstance(meta, dict) or meta.get(META_KEY) is None:
        return NONE
    n = checked(_meta_float(meta[META_KEY], META_KEY), f"metadata {META_KEY}")
    ci = meta.get(META_CI)
    if isinstance(ci, str):
        parts = [p for p in ci.replace("[", "").replace("]", "").split(",") if p.strip()]
        ci = [_meta_float(p, META_CI) for p in parts]
    source = meta.get(META_SOURCE)
    origin = meta.get(META_ORIGIN) if meta.get(META_ORIGIN) in ("given", "device") else "given"
    return DeviceFriction(n, checked_ci(ci, n, f"metadata {META_CI}"),
                          source if isinstance(source, str) and source else "given in the metadata",
                          origin)


def _meta_float(x, key: str) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        raise UserError(f"metadata {key}={x!r} is not a number") from None
