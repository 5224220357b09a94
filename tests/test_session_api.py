"""labbench.load: a session or CSV as one object whose analyses are `labbench analyze`'s numbers."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import labbench
from labbench.cli import main
from labbench.errors import MissingExtraError, UserError
from labbench.sessions.export import export_csv
from sim_sessions import TRUTH, record_session


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("api")
    return {"chirp": record_session(d, "chirp-id", duration_s=8.0, f0_hz=0.5)[0],
            "etfe": record_session(d, "etfe", duration_s=15.0, seed=2)[0]}


def _cli_json(capsys, *argv) -> dict:
    capsys.readouterr()
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def _as_json(d: dict) -> dict:
    from labbench.jsonutil import json_safe

    return json.loads(json.dumps(json_safe(d)))


def test_import_labbench_is_light():
    code = ("import sys, labbench; heavy = [m for m in ('numpy', 'scipy', 'matplotlib', "
            "'labbench.session_api') if m in sys.modules]; print(heavy); "
            "assert callable(labbench.load); assert 'labbench.session_api' in sys.modules")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_session_contents(sessions):
    s = labbench.load(sessions["chirp"])
    assert s.meta["protocol"] == "chirp-id" and s.meta["fs"] == pytest.approx(1000.0)
    assert s.meta["status"] == "success" and s.meta["device"] == "sim"
    assert s.meta["started"][:2] == "20" and s.meta["started"][10] == "T"
    for name in ("t", "position", "excitation", "ve_force", "command", "force"):
        assert s.data[name].shape == s.data["t"].shape
    assert s.units["position"] == "m" and s.units["force"] == "N" and s.units["t"] == "s"
    assert np.all(np.diff(s.data["t"]) > 0)
    assert s.records["stop"]["status"] == "success"
    assert "chirp-id" in repr(s)


@pytest.mark.parametrize("options, argv", [({}, []), ({"method": "l1", "model": "mb"},
                                                    ["--method", "l1", "--model", "mb"])])
def test_identify_is_analyze_id(sessions, capsys, options, argv):
    path = sessions["chirp"]
    fit = labbench.load(path).identify(**options)
    cli = _cli_json(capsys, "analyze", "id", str(path), "--json", *argv)
    assert _as_json(fit.as_dict()) == cli  # exactly the same numbers
    assert (fit.m, fit.b) == (cli["m"], cli["b"])
    assert fit.m == pytest.approx(TRUTH["m"], rel=1e-3)
    assert fit.b == pytest.approx(TRUTH["b"], rel=2e-2)
    assert tuple(cli["ci95"]["m"]) == fit.ci95["m"]


def test_etfe_is_analyze_etfe(sessions, capsys, tmp_path):
    path = sessions["etfe"]
    fr = labbench.load(path).etfe(m=TRUTH["m"], b=TRUTH["b"])
    cli = _cli_json(capsys, "analyze", "etfe", str(path), "--json", "--m", "0.094", "--b", "0.1")
    assert _as_json(fr.as_dict()) == cli
    np.testing.assert_array_equal(fr.ES, cli["ES"])
    np.testing.assert_array_equal(fr.Z.real, cli["Z_re"])
    assert fr.wb_star == cli["wb_star"] and fr.ws_star == cli["ws_star"]
    # the spring K = 50 N/m shows at low frequency (within 5 % at 3 rad/s, well below ws*)
    k = np.argmin(abs(fr.w - 3.0))
    assert fr.ES[k] == pytest.approx(50.0, rel=0.05)
    fig = fr.plot(tmp_path / "fr.png")
    assert (tmp_path / "fr.png").stat().st_size > 10_000 and len(fig.axes) == 5


def test_csv_gives_the_session_numbers(sessions, tmp_path, capsys):
    csv = export_csv(sessions["chirp"], tmp_path / "chirp.csv")
    table, session = labbench.load(csv), labbench.load(sessions["chirp"])
    assert set(table.data) >= {"t", "force", "position", "velocity", "command"}
    np.testing.assert_array_equal(table.data["position"], session.data["position"])
    assert table.units["velocity"] == "m/s"
    assert table.identify().as_dict()["m"] == session.identify().m
    assert _as_json(table.identify().as_dict()) == _cli_json(capsys, "analyze", "id", str(csv), "--json")


def test_plot_and_dataframe(sessions, tmp_path, monkeypatch):
    s = labbench.load(sessions["chirp"])
    fig = s.plot(tmp_path / "s.png")
    assert len(fig.axes) == 2 and (tmp_path / "s.png").stat().st_size > 5_000
    df = s.to_dataframe()
    assert list(df["position"]) == list(s.data["position"]) and df.attrs["units"]["t"] == "s"
    monkeypatch.setitem(sys.modules, "pandas", None)  # as if not installed
    with pytest.raises(MissingExtraError, match=r"pip install 'haptic-labbench\[pandas\]'"):
        s.to_dataframe()


def test_errors_are_one_line(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        labbench.load(tmp_path / "missing.lbsession")
    bad = tmp_path / "x.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(UserError, match="missing column"):
        labbench.load(bad)


# ----------------------------------------------------------------------------- progress, cancel
class _CountingEvent:
    """A cancel event that reads as set from its ``at``-th check on (never, when None),
    counting the checks."""

    def __init__(self, at: int | None = None):
        self.at, self.calls = at, 0

    def is_set(self) -> bool:
        self.calls += 1
        return self.at is not None and self.calls >= self.at


ANALYSES = {
    "etfe paper --fit": lambda s, **kw: s.etfe(estimator="paper", window=20, fit=True, **kw),
    "etfe lpm --fit": lambda s, **kw: s.etfe(fit=True, **kw),
    "etfe h1-welch": lambda s, **kw: s.etfe(estimator="h1-welch", **kw),
    "id l1": lambda s, **kw: s.identify(method="l1", **kw),
    "id l2 (closed loop)": lambda s, **kw: s.identify(**kw),
}


def _session_for(name, sessions):
    return labbench.load(sessions["chirp" if name == "id l1" else "etfe"])


@pytest.mark.parametrize("name", ANALYSES)
def test_progress_is_monotone_from_0_to_1_with_phrases(sessions, name):
    heard = []
    result = ANALYSES[name](_session_for(name, sessions), progress=lambda f, p: heard.append((f, p)))
    fractions = [f for f, _ in heard]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0 and len(heard) >= 4
    assert all(0.0 <= a <= b <= 1.0 for a, b in zip(fractions, fractions[1:])), fractions
    assert all(isinstance(p, str) and 0 < len(p) < 60 for _, p in heard)
    # reporting changes nothing: the same numbers as without a callback
    plain = ANALYSES[name](_session_for(name, sessions))
    assert json.dumps(_as_json(plain.as_dict())) == json.dumps(_as_json(result.as_dict()))


@pytest.mark.parametrize("name", ANALYSES)
def test_cancel_stops_at_every_check(sessions, name):
    # a set event raises Cancelled at whichever check sees it first: from before any work to
    # the last step (checks counted on a run that is never cancelled)
    from labbench.errors import Cancelled, LabbenchError

    session = _session_for(name, sessions)
    count = _CountingEvent()
    ANALYSES[name](session, cancel=count)
    assert count.calls >= 4
    for at in sorted({1, 2, count.calls // 3, count.calls // 2, count.calls - 1, count.calls}):
        event = _CountingEvent(at)
        with pytest.raises(Cancelled):
            ANALYSES[name](session, cancel=event)
        assert event.calls == at  # stopped at the check that saw it, nothing after
    assert issubclass(Cancelled, LabbenchError)


def test_cancel_with_a_real_event_from_another_thread(sessions):
    import threading

    from labbench.errors import Cancelled

    session = labbench.load(sessions["etfe"])
    cancel = threading.Event()
    outcome = []

    def work():
        try:
            session.etfe(estimator="paper", window=20, fit=True, cancel=cancel,
                         progress=lambda f, p: cancel.set() if f >= 0.5 else None)
        except Cancelled as exc:
            outcome.append(exc)

    t = threading.Thread(target=work)
    t.start()
    t.join(60)
    assert not t.is_alive() and len(outcome) == 1


def test_cli_maps_cancelled_like_an_interrupt(sessions, capsys, monkeypatch):
    from labbench import session_api
    from labbench.errors import Cancelled

    def cancelled(*a, **kw):
        raise Cancelled("analysis cancelled")

    monkeypatch.setattr(session_api, "etfe_recording", cancelled)
    capsys.readouterr()
    assert main(["analyze", "etfe", str(sessions["etfe"])]) == 130
    err = capsys.readouterr().err
    assert "analysis cancelled" in err and "Traceback" not in err
