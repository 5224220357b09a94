"""Every option of every command says what it is for (issue 30): the whole argparse tree is
walked, and the protocol options' help is the protocol's own field description."""
from __future__ import annotations

import argparse
import re
from dataclasses import fields

import pytest

from labbench.cli.main import build_parser
from labbench.protocol import field_choices, field_help
from labbench.registry import protocol_class, protocol_names

# A help that only restates the default says nothing about the option.
_EMPTY = re.compile(r"\s*(\(?default:? [^\s;,)]*\)?)?\s*")


def _walk(parser, path):
    """(command path, parser, action) for every action of every (sub)parser."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield path, parser, ("command", name, helps.get(name))
                yield from _walk(sub, [*path, name])
        elif not isinstance(action, argparse._HelpAction):
            yield path, parser, action


def _empty(text) -> bool:
    return text is None or text is argparse.SUPPRESS or bool(_EMPTY.fullmatch(str(text)))


def test_every_option_of_every_command_has_help():
    seen, missing = 0, []
    for path, parser, action in _walk(build_parser(), ["labbench"]):
        seen += 1
        if isinstance(action, tuple):
            _, name, text = action
            what = f"{' '.join(path)} {name}"
        else:
            text = action.help
            what = f"{' '.join(path)} {'/'.join(action.option_strings) or action.dest}"
        if _empty(text):
            missing.append(what)
    assert seen > 150  # the walk reached the protocols' options
    assert missing == []


def test_every_help_page_renders():
    """argparse formats help lazily: a stray % in a description would raise only there."""
    pages = [build_parser()]
    while pages:
        p = pages.pop()
        assert p.format_help()
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                pages.extend(action.choices.values())


@pytest.mark.parametrize("name", protocol_names())
def test_protocol_fields_are_described_once(name):
    """Each config field has a description (the GUI's tooltip), and `run NAME --help` shows
    that same text: meaning, unit, choices, default."""
    config_cls = protocol_class(name).Config
    described = field_help(config_cls)
    assert set(described) == {f.name for f in fields(config_cls)}
    assert [k for k, v in described.items() if not v] == []
    run = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    sub = next(a for a in run.choices["run"]._actions if isinstance(a, argparse._SubParsersAction))
    options = {a.dest: a for a in sub.choices[name]._actions}
    for f in fields(config_cls):
        if f.name == "sample_time_s":  # set from the rig, not an option
            assert f.name not in options
            continue
        assert options[f.name].help.replace("%%", "%") == described[f.name]
        assert "default " in described[f.name]
    for field_name, choices in field_choices(config_cls).items():
        assert all(c in described[field_name] for c in choices)


def test_a_description_names_unit_choices_and_default():
    from labbench.protocols.white_noise import EtfeConfig

    text = field_help(EtfeConfig)
    assert text["std_n"] == ("standard deviation of the white-noise excitation force [N]; "
                             "default 0.5")
    assert "[rad/s]" in text["w0_rad_s"] and "none: no filter" in text["w0_rad_s"]
    from labbench.analysis.etfe import ESTIMATORS

    assert field_choices(EtfeConfig)["estimator"] == ESTIMATORS
    assert text["allow_unstable"].endswith("default off")


def test_an_undescribed_field_reads_empty():
    """The check above can fail: a plug-in's field without a description is found."""
    from dataclasses import dataclass

    from labbench.protocol import Config

    @dataclass(frozen=True)
    class Plugin(Config):
        K: float = 1.0
        gain_x: float = 2.0

        def check(self):
            pass

    assert field_help(Plugin) == {"K": "virtual stiffness [N/m]; default 1", "gain_x": ""}
