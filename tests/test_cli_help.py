"""Each ``lidarscan COMMAND --help`` ends with examples, and every example is a command line
the parser accepts (options and values as they are spelled today)."""

from __future__ import annotations

import shlex

import pytest

from converters.cli import build_parser
from converters.cli._examples import EXAMPLES


def example_lines(command: str) -> list[list[str]]:
    """The argv (without ``lidarscan``) of every example of ``command``."""
    out = []
    for line in EXAMPLES[command].splitlines()[1:]:
        argv = shlex.split(line.partition("#")[0])
        assert argv[:2] == ["lidarscan", command], line
        out.append(argv[1:])
    return out


@pytest.mark.parametrize("command", ["demo", "info", "convert", "view"])
def test_help_ends_with_examples_the_parser_accepts(
        command: str, capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    with pytest.raises(SystemExit) as exc:
        parser.parse_args([command, "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert text.rstrip().endswith(EXAMPLES[command].rstrip())    # printed as written
    examples = example_lines(command)
    assert examples
    for argv in examples:
        args = parser.parse_args(argv)          # SystemExit(2) on an option that is gone
        assert args.command == command
