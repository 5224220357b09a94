"""Verdicts (labbench.verdict): the worst finding wins, reasons kept, hostile dicts refused."""
import pytest

from labbench import verdict
from labbench.verdict import DOUBTFUL, FAILED, OK, Verdict


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
