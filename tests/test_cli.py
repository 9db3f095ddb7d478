"""`netpose <command> --help` answers for every command and sub-command.

argparse expands `%` in help strings, so a literal "25 % of a core" crashes the help of the
whole command group with a TypeError; nothing but formatting every parser finds that.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from service.cli import COMMANDS, build_parser


def _all_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found.extend(_all_parsers(sub))
    return found


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_help_text_formats(command: str) -> None:
    parsers = _all_parsers(build_parser([command]))
    assert len(parsers) >= 2  # the top level and the command's own parser, at least
    for parser in parsers:
        text = parser.format_help()
        assert parser.prog in text


def test_bench_help_answers_from_the_installed_command() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "bench", "--help"],
        capture_output=True, text=True, timeout=60, check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "soak" in done.stdout and "Traceback" not in done.stderr
