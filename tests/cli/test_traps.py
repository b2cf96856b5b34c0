"""The command line's traps for a newcomer: each a test that failed before it was fixed."""

from __future__ import annotations

import pytest

from vlmproprio.cli import main
from vlmproprio.cli.texts import MAINTAINER_COMMANDS
from vlmproprio.conditions import CONTROLS


def _help(capsys, *args: str) -> str:
    with pytest.raises(SystemExit):
        main([*args, "--help"])
    return capsys.readouterr().out


def test_top_level_help_counts_the_controls_and_keeps_maintainer_commands_apart(capsys) -> None:
    text = _help(capsys)
    words = ("no", "one", "two", "three", "four", "five", "six", "seven")
    assert f"{words[len(CONTROLS)]} controls" in text
    listed = text.split("options:")[0]
    for name in MAINTAINER_COMMANDS:
        assert f"\n    {name} " not in listed and f"\n    {name}\n" not in listed  # not among the user commands
        assert name in text.split("maintainer commands")[1]  # but named
        assert "usage: vlmproprio " + name in _help(capsys, name)  # and still there


def test_every_command_has_a_description(capsys) -> None:
    for name in ("verify", "manifest", "run", "score", "report", "leaderboard"):
        text = _help(capsys, name)
        assert text.split("\n\n")[1].strip() and not text.split("\n\n")[1].startswith(("options:", "positional")), name


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["run", "--model", "refernce"], "did you mean 'reference'"),
        (["run", "--model", "reference", "--conditions", "bothh"], "did you mean 'both'"),
        (["run", "--model", "reference", "--episodes", "door00"], "did you mean 'door_00'"),
        (["run", "--model", "reference", "--k", "0"], "--k must be"),
        (["run", "--model", "reference", "--frame-stride", "0"], "--frame-stride must be"),
    ],
)
def test_wrong_values_name_the_flag_or_the_likely_name(args, expected, capsys, tmp_path) -> None:
    assert main([*args, "--out", str(tmp_path / "run")]) == 2
    assert expected in capsys.readouterr().err


def _parsers():
    import argparse

    from vlmproprio.cli.parser import build_parser

    todo = [("vlmproprio", build_parser())]
    while todo:
        name, p = todo.pop()
        yield name, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                todo += [(f"{name} {n}", sp) for n, sp in a.choices.items()]


def test_one_metavar_style_and_no_option_that_swallows_a_positional() -> None:
    for name, p in _parsers():
        positionals = [a for a in p._actions if not a.option_strings and a.nargs != 0 and a.dest != "command"]
        for a in p._actions:
            if not a.option_strings or a.nargs == 0 or a.choices or a.help == "==SUPPRESS==":
                continue
            metavars = a.metavar if isinstance(a.metavar, tuple) else (a.metavar,)
            for m in metavars:
                # a word for the value (N, DIR, URL ...), not argparse's default, the destination (FRAME_STRIDE)
                assert m and m.isupper() and ("_" not in m or m == "RUN_DIR"), (name, a.option_strings, m)
            if positionals:
                assert a.nargs not in ("+", "*"), f"{name} {a.option_strings[0]} would swallow {positionals[0].dest}"


def test_export_dataset_episodes_before_out(tmp_path, capsys) -> None:
    pytest.importorskip("datasets", reason="the export needs the [dataset] extra")
    out = tmp_path / "out"
    assert main(["export-dataset", "--episodes", "door_00", str(out)]) == 0
    assert (out / "README.md").is_file()
