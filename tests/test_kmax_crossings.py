"""k_max found from the unit-circle crossings of the loop (labbench.model.linear._crossings)
against the plain scan it falls back to: the same boundary over random loops, in a tenth of
the stability checks."""
import math
import random

import pytest

from labbench.model import linear
from labbench.model.ve import Plant, VirtualEnvironment


def loops(n, seed):
    rng = random.Random(seed)
    out = []
    while len(out) < n:
        T = 10 ** rng.uniform(-4.5, -2)
        kind = rng.choice(["spring", "spring-damper"])
        b = 10 ** rng.uniform(-3, 1) if rng.random() < 0.9 else 0.0
        B = 10 ** rng.uniform(-2, 1) if kind != "spring" else 0.0
        w0 = 10 ** rng.uniform(0.5, 4) if rng.random() < 0.8 else math.inf
        try:
            out.append((Plant(10 ** rng.uniform(-3, 1), b),
                        VirtualEnvironment(kind, K=1.0, B=B, w0=w0, T=T,
                                           td=T * rng.choice([0, 0, 1, 2, 5])),
                        T * rng.choice([0, 0, 0.5, 1, 2.3])))
        except Exception:  # a draw outside the physical ranges
            continue
    return out


def test_crossings_and_scan_find_the_same_boundary(monkeypatch):
    """120 random loops (m, b, T, td, device delay, B, w0 over decades): both ways within
    2 rel_tol of each other (each is within rel_tol below the true boundary); the crossings
    take < 12 stability checks a loop on average where the scan takes ~70."""
    calls = {"n": 0}
    stability = linear.stability

    def counted(*a, **k):
        calls["n"] += 1
        return stability(*a, **k)

    monkeypatch.setattr(linear, "stability", counted)
    fast = []
    for plant, ve, lat in loops(120, 3):
        calls["n"] = 0
        fast.append((linear.k_max(plant, ve, latency=lat), calls["n"]))
    monkeypatch.setattr(linear, "_crossings", lambda *a: [])  # the scan alone
    for (plant, ve, lat), (k, _) in zip(loops(120, 3), fast):
        scan = linear.k_max(plant, ve, latency=lat)
        assert k == scan or k == pytest.approx(scan, rel=2.1e-4), (plant, ve, lat)
    assert sum(n for _, n in fast) / len(fast) < 12


def test_a_missed_crossing_falls_back_to_the_scan(monkeypatch):
    """Crossings that are wrong (here: one far below the boundary, where the loop is still
    stable above it) leave the answer to the scan."""
    plant, ve = Plant(0.094, 0.1), VirtualEnvironment("spring-damper", K=1.0, B=1.0, w0=125.0)
    truth = linear.k_max(plant, ve)
    monkeypatch.setattr(linear, "_crossings", lambda *a: [0.5 * truth])
    assert linear.k_max(plant, ve) == pytest.approx(truth, rel=2.1e-4)
