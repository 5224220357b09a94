"""The theory numbers a person reads: one place for the live labels, the overlays, the
Identification tab, the report and the CLI.

The prediction is the exact sampled model (``labbench.model.linear.z_sampled``) with the
rig's device delay (``labbench.model.device_delay``), its bandwidths read off its own ES and
ED curves with the rules applied to measurements (``labbench.model.linear.predicted_bandwidths``).
The paper's continuous closed forms, sqrt(K/m) (eq. 5) and w0 (sec. 3.2), are kept
beside it and always labelled as such: on the paper's demo (K = 50 N/m, B = 1 N s/m,
w0 = 125 rad/s, 1 kHz) the sampled model's w_b* is 72.6 rad/s where w0 says 125, and a
window that showed w0 as "theory" read as a far-off measurement.
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np

from labbench.model.effective import effective_impedances, measured_wb_star, measured_ws_star
from labbench.model.ve import Plant, VirtualEnvironment

SYMBOLS = {"ws": "w_s*", "wb": "w_b*"}
CLOSED_FORM = {"ws": "paper eq. 5", "wb": "paper w0"}


@dataclass(frozen=True)
class Bandwidths:
    """Predicted bandwidths [rad/s] of one VE on one plant (None: the curve never crosses,
    or the VE has no spring / no virtual damping).

    ``ws_star`` / ``wb_star``: from ``model`` ("sampled"; "paper" when td is not whole
    samples and no sampled model exists) with ``latency_s``; ``ws_star_eq5`` /
    ``wb_star_w0``: the paper's continuous closed forms.
    """

    ws_star: float | None
    wb_star: float | None
    ws_star_eq5: float | None
    wb_star_w0: float | None
    model: str
    latency_s: float

    def as_dict(self) -> dict:
        return asdict(self)

    def predicted(self, which: str) -> float | None:
        return self.ws_star if which == "ws" else self.wb_star

    def closed_form(self, which: str) -> float | None:
        return self.ws_star_eq5 if which == "ws" else self.wb_star_w0


def recorded_plant(start: dict, results: dict | None = None) -> Plant | None:
    """The device model a session's theory uses: its analysis' (``results["plant"]``)
    first, then the one its pre-check and start record name; None when it names none."""
    start = start if isinstance(start, dict) else {}
    for p in ((results or {}).get("plant"), (start.get("precheck") or {}).get("plant"),
              start.get("plant")):
        if isinstance(p, dict) and "m" in p and "b" in p:
            return Plant(float(p["m"]), float(p["b"]))
    return None


@functools.lru_cache(maxsize=64)
def bandwidths(plant: Plant, ve: VirtualEnvironment, latency_s: float = 0.0) -> Bandwidths:
    """The predicted bandwidths of ``ve`` on ``plant`` with the device delay ``latency_s``
    [s]; cached (the window asks for them at every estimate)."""
    from labbench.model import linear

    model = "sampled" if linear.whole_samples(ve) else "paper"
    read = linear.predicted_bandwidths(plant, ve, model, latency_s)
    return Bandwidths(read["ws_star"], read["wb_star"], linear.predicted_ws_star(plant, ve),
                      linear.predicted_wb_star(ve), model, float(latency_s))


def measured(w, Z, b: float, low: dict | None) -> tuple[float | None, float | None]:
    """The measured (w_s*, w_b*) [rad/s] of an estimate ``Z`` on ``w``, read as the rendered
    stiffness and damping are (``low``: the rendered impedance of
    ``labbench.analysis.rendered``, its ED(0) ``B`` and the ``band_rad_s`` it was read over):
    from the low edge of that band up, w_s* where ES falls through zero and w_b* where ED has
    fallen half-way from ``B`` to the device's ``b`` (Colonnese et al. sec. 3). The lowest
    bins of a drifting record hold its edge leakage: read from there (ED's three lowest
    bins as the reference), an h1-welch run's w_b* was 1.04 rad/s where the exact sampled
    theory says 72.6 (now 66.6; lpm 72.57 both ways). None without ``low`` (no rendered
    impedance: the record does not reach the VE's bandwidths)."""
    if not isinstance(low, dict) or low.get("B") is None or not low.get("band_rad_s"):
        return None, None
    w, Z = np.asarray(w, float), np.asarray(Z, complex)
    above = w >= float(low["band_rad_s"][0])
    eff = effective_impedances(w[above], Z[above])
    return (measured_ws_star(eff.w, eff.ES),
            measured_wb_star(eff.w, eff.ED, b, reference=float(low["B"])))


def read(w, Z, felt: Plant, ve: VirtualEnvironment, latency_s: float, low: dict | None) -> dict:
    """A rendered VE's bandwidths as its results keep them (``bandwidths``: the report's
    table, the CLI's rows, the window's marks): ``measured`` on the plant compared with
    (``felt``: its b is where ED falls to) beside the prediction of ``bandwidths``."""
    ws, wb = measured(w, Z, felt.b, low)
    bw = bandwidths(felt, ve, latency_s)
    return {"ws_star_measured": ws, "ws_star_predicted": bw.ws_star, "ws_star_eq5": bw.ws_star_eq5,
            "wb_star_measured": wb, "wb_star_predicted": bw.wb_star, "wb_star_w0": bw.wb_star_w0}


def of_results(d, ve: VirtualEnvironment, latency_s: float) -> tuple[float | None, float | None,
                                                                   Bandwidths | None]:
    """(w_s*, w_b* measured, the prediction) as ``read`` kept them in a result's
    ``bandwidths`` ``d``; what the window marks on a finished record. Nones when ``d`` holds
    none."""
    from labbench.model import linear

    if not isinstance(d, dict) or not any(k in d for k in ("ws_star_measured", "wb_star_measured")):
        return None, None, None
    num = {k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None)
           for k, v in d.items()}
    pred = Bandwidths(num.get("ws_star_predicted"), num.get("wb_star_predicted"),
                      num.get("ws_star_eq5"), num.get("wb_star_w0"),
                      "sampled" if linear.whole_samples(ve) else "paper", float(latency_s))
    return num.get("ws_star_measured"), num.get("wb_star_measured"), pred
