"""Every option of every ``usp-jax`` command explains itself: a help text, its default, and for
``--weights`` the names that exist. Walking the parser makes a future option without help fail."""

import argparse
import pathlib
import re

import pytest

from usp_jax.cli.parser import build_parser
from usp_jax.inference.weights import PRETRAINED


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (subparsers,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {"usp-jax": parser, **subparsers.choices}


def _arguments(parser: argparse.ArgumentParser):
    """Every option and positional a user can give (not -h, not the subcommand choice)."""
    for action in parser._actions:
        if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            yield action


def _name(action) -> str:
    return "/".join(action.option_strings) or action.dest


COMMANDS = _commands()


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_option_has_help_and_its_default(command):
    parser = COMMANDS[command]
    missing = [_name(a) for a in _arguments(parser) if not (a.help or "").strip()]
    assert not missing, f"{command}: options without help: {missing}"
    text = parser.format_help()
    for action in _arguments(parser):
        if action.option_strings and action.nargs != 0 and action.default not in (None, False):
            # The help as shown, %(default)s expanded, states the default.
            shown = parser._get_formatter()._expand_help(action)
            assert "default" in shown, f"{command} {_name(action)}: no default in {shown!r}"
    assert "%(" not in text


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_no_flag_claims_a_default_value(command):
    """A flag takes no value, so "(default: True)" after ``--no-refine`` would read as "refinement
    off by default", the opposite of what it means."""
    for action in _arguments(COMMANDS[command]):
        if action.nargs == 0:
            shown = COMMANDS[command]._get_formatter()._expand_help(action)
            assert "(default: True)" not in shown, f"{command} {_name(action)}: {shown!r}"


def test_no_refine_leaves_the_choice_to_the_weights_unless_given():
    parser = COMMANDS["evaluate"]
    assert parser.parse_args(["--hpatches", "x"]).refine is None
    assert parser.parse_args(["--hpatches", "x", "--no-refine"]).refine is False
    assert parser.parse_args(["--hpatches", "x", "--refine"]).refine is True


def test_weights_help_names_every_shipped_weights():
    helps = {
        command: action.help
        for command, parser in COMMANDS.items()
        for action in _arguments(parser)
        if "--weights" in action.option_strings
    }
    assert {"evaluate", "detect", "match", "benchmark", "export", "demo"} <= set(helps)
    for command, text in helps.items():
        absent = [name for name in PRETRAINED if name not in text]
        assert not absent, f"{command} --weights help lacks {absent}"


def test_detect_and_match_state_their_point_counts():
    for command in ("detect", "match"):
        (top,) = (a for a in _arguments(COMMANDS[command]) if "--top" in a.option_strings)
        assert f"default {top.default}" in top.help


def test_help_formatter_adds_a_missing_default():
    """An option whose help forgets its default gets one appended; one that states it does not."""
    parser = build_parser()
    parser.add_argument("--forgot", type=int, default=7, help="a number")
    parser.add_argument("--stated", type=int, default=8, help="a number (default 8)")
    text = " ".join(parser.format_help().split())
    assert "a number (default: 7)" in text
    assert "a number (default 8)" in text and "(default: 8)" not in text


def test_demo_help_states_the_time_the_readme_states():
    text = " ".join(COMMANDS["usp-jax"].format_help().split())
    (duration,) = re.findall(r"demo .*?(about \d+ s on 2 idle CPU cores)", text)
    readme = pathlib.Path(__file__).resolve().parents[1] / "README.md"
    assert duration in " ".join(readme.read_text().split())


@pytest.mark.parametrize("command", sorted(set(COMMANDS) - {"usp-jax"}))
def test_each_command_help_opens_with_what_it_does(command):
    assert COMMANDS[command].description
