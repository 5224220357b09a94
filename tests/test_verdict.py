"""Verdicts (labbench.readout.verdict): the worst finding wins, reasons kept, hostile dicts refused."""
import pytest

from labbench.readout import verdict
from labbench.readout.verdict import DOUBTFUL, FAILED, OK, Verdict


def test_the_worst_finding_sets_the_level_and_only_bad_findings_give_reasons():
    v = verdict.judge([(OK, "chi2/dof 1.0"), (DOUBTFUL, "coherence 0.8 at 40 rad/s"),
                       (FAILED, "td at its bound")])
    assert v == Verdict(FAILED, ("coherence 0.8 at 40 rad/s", "td at its bound"))
    assert verdict.judge([(OK, "fine")]) == Verdict()
    assert v.line() == "failed: coherence 0.8 at 40 rad/s; td at its bound"
    assert Verdict().line() == "ok"
    with pytest.raises(ValueError):
        verdict.judge([("bad", "x")])
    with pytest.raises(ValueError):
        Verdict("great")


def test_worst_of_several_results():
    a, b = Verdict(DOUBTFUL, ("a",)), Verdict(FAILED, ("b",))
    assert verdict.worst([a, None, b, Verdict()]) == Verdict(FAILED, ("a", "b"))
    assert verdict.worst([]) == Verdict()
    assert verdict.worst([Verdict(DOUBTFUL)]).level == DOUBTFUL


def test_round_trip_and_hostile_content():
    v = Verdict(DOUBTFUL, ("x",))
    assert verdict.from_dict(v.as_dict()) == v
    for bad in ("ok", None, [], {"level": "fine"}, {"level": 3}, {}):
        assert verdict.from_dict(bad) is None
    assert verdict.from_dict({"level": "failed", "reasons": "x"}) == Verdict(FAILED)
    got = verdict.from_dict({"level": "ok", "reasons": [1, "y", None] + ["z"] * 100})
    assert got.reasons[0] == "y" and len(got.reasons) <= verdict.MAX_REASONS


def test_strict_exit():
    assert verdict.strict_exit([Verdict(FAILED)], strict=True) == verdict.STRICT_EXIT == 3
    assert verdict.strict_exit([Verdict(FAILED)], strict=False) == 0
    assert verdict.strict_exit([Verdict(DOUBTFUL), None], strict=True) == 0


def test_a_number_is_vouched_for_when_its_999_interval_is_within_the_target():
    # 95 % half-width 1.0 -> 1.68 at 99.9 %: within a target of 2, not within 1.5
    assert verdict.unvouched("m", 10.0, (9.0, 11.0), 2.0)[0] == OK
    level, reason = verdict.unvouched("m", 10.0, (9.0, 11.0), 1.5, " kg")
    assert level == DOUBTFUL and reason.startswith("m not pinned to its accuracy target +-1.5 kg")
    # asymmetric intervals count by their longer side; a nan interval is never vouched for
    assert verdict.unvouched("b", 1.0, (0.0, 1.1), 1.0)[0] == DOUBTFUL
    assert verdict.unvouched("b", 1.0, (float("nan"), 1.1), 1.0)[0] == DOUBTFUL


def test_a_subset_of_the_method_map_grid_has_no_silent_failure():
    # bench/bench_coverage.py's own cells and definitions, two records each where the methods
    # are pushed (force noise, friction, an unstated delay, a sharp resonance, sensor noise, a
    # weak spring that cannot place its delays): every result outside its target says why
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import bench_coverage as grid

    rows = [grid.id_task(cell, "l2", seed) for seed in (0, 1) for cell in (
        "chirp 30 s, force noise 0.2 N", "Coulomb 0.2 N, 0.02 N", "device one period late, unstated, 0.02 N",
        "closed loop (spring-damper), process 0.1 N")]
    rows += [grid.loop_task(*cell, seed) for seed in (0, 1) for cell in (
        ("spring K 10", "both 1.3 + 2.7", "sensor 0.05 N", 20000),
        ("damper B 1.5", "VE path 1.75", "process 0.1 N", 20000))]
    for r in rows:
        assert not r["miss"] or (r["level"] != "ok" and r["why"]), r
    # the grid does push them past their targets (where their intervals say so, that is no miss)
    assert sum(bool(r["beyond"]) for r in rows) >= 4
    bands = [grid.etfe_task(ve, noise, "30 s", "lpm", seed) for seed in (0, 1) for ve, noise in (
        ("spring K 180 (0.9 K_max)", "position 1e-5 m"), ("spring-damper K 50", "sensor 0.05 N on 0.25 N"))]
    for r in bands:
        assert not r["far"] or r["level"] != "ok", r
        assert 0.85 <= r["inside"] / r["n"] <= 1.0, r  # a 95 % band, ~65 frequencies
