"""`fpe`'s own face: --version, help that says every option's default and ends with an example
of the command, and docs/commands.md showing that help as it is."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from fpe_jax import __version__
from fpe_jax.cli import _build_parser, main


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = _build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out == f"fpe {__version__}\n"


@pytest.mark.parametrize("name", sorted(_subparsers()))
def test_help_says_every_default_and_ends_with_an_example(name):
    parser = _subparsers()[name]
    text = parser.format_help()
    last = text.rstrip().splitlines()
    assert last[-2] == "example:" and last[-1].startswith(f"  fpe {name}"), text
    formatter = parser._get_formatter()
    for action in parser._actions:
        if not action.option_strings or isinstance(action, argparse._HelpAction):
            continue
        said = formatter._get_help_string(action)
        assert "default" in said or said.endswith("(required)"), (name, action.option_strings)
        if action.default not in (None, False):
            assert str(action.default) in said, (name, action.option_strings, said)


def test_the_commands_reference_shows_each_commands_help_as_it_is(monkeypatch):
    """docs/commands.md holds every command's `--help` at 100 columns, as `fpe` prints it."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "commands.md").read_text()
    shown = dict(re.findall(r"### fpe (\S+)\n\n```\n(usage: fpe .*?)```", doc, re.S))
    parsers = _subparsers()
    assert shown.keys() == parsers.keys()
    monkeypatch.setenv("COLUMNS", "100")  # argparse wraps help to the terminal's width
    for name, parser in parsers.items():
        assert shown[name] == parser.format_help(), name


def _only(word: str) -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in _build_parser(word)._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


@pytest.mark.parametrize("name", sorted(_subparsers()))
def test_the_parser_of_one_command_is_that_part_of_the_whole(name):
    """`main` builds the parser of the command it runs: the same help, so the same arguments."""
    only = _only(name)
    assert list(only) == [name]
    assert only[name].format_help() == _subparsers()[name].format_help()


def test_the_parser_of_one_command_parses_as_the_whole():
    line = ["predict", "d.mcap", "--waypoints", "w.csv", "--out", "p.csv", "--dt", "0.05"]
    assert vars(_build_parser("predict").parse_args(line)) == vars(_build_parser().parse_args(line))


@pytest.mark.parametrize("word", ["nosuch", "--help", "-h", "--quiet"])
def test_a_word_that_names_no_command_gets_the_whole_parser(word):
    assert _only(word).keys() == _subparsers().keys()


@pytest.mark.parametrize("command", ["predict", "plot", "run", "node"])
def test_the_fpe_process_runs_the_collectors_young_passes_less_often(command):
    """`entry` (the `fpe` script) raises the young generation's threshold before `main` imports
    JAX and matplotlib, except for the commands that answer a stream as long as it lasts;
    importing the module (as the library's callers do) changes nothing."""
    from fpe_jax import cli

    code = (
        "import gc, fpe_jax.cli as c\n"
        "before = gc.get_threshold()\n"
        "c.main = lambda: print(*before, *gc.get_threshold()) or 0\n"
        "c.entry()\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, command], capture_output=True, text=True, check=True
    )
    values = [int(v) for v in out.stdout.split()]
    before, during = values[:3], values[3:]
    assert before[0] < cli.GC_YOUNG_THRESHOLD
    raised = [cli.GC_YOUNG_THRESHOLD, *before[1:]]
    assert during == (before if command in cli.STREAM_COMMANDS else raised)
