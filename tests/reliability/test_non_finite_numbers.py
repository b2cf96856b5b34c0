"""Issue 36, item 7: NaN and infinity are refused by every numeric option and variable, in one line naming it.

Python's ``float`` reads "nan", "inf", "-inf", "Infinity" and "1e999" (which overflows to inf), and a range check
(``x < 0 or x > 1``) is false for NaN: ``score --threshold nan`` passed its [0, 1] check and wrote no boundaries
and F1 0. The options are not listed here by hand: every option of every command (maintainer commands and
``cassette`` sub-commands included) whose value is a number is found in the parser and given each spelling,
so an option added later is checked too. Each must exit 2 with one ``vlmproprio: error:`` line naming the
option, before the command writes anything. The numeric environment variable (``$VLMPROPRIO_WORKERS``) is
given the same spellings.
"""

from __future__ import annotations

import argparse

import pytest
from fault_support import cli_in_process
from reliability_support import assert_one_line_error

from vlmproprio.cli.parser import build_parser

NON_FINITE = ("nan", "NaN", "inf", "-inf", "+Infinity", "1e999", "-1e999")


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command words, its parser) for every sub-command, nested ones (``cassette export``) included."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs and path:
        yield path, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _commands(sub, (*path, name))


def _required(parser: argparse.ArgumentParser, skip: argparse.Action) -> list[str]:
    """The least arguments that let ``parser`` parse: a placeholder for each positional and required option."""
    out: list[str] = []
    for a in parser._actions:
        if a is skip or isinstance(a, argparse._HelpAction) or not (a.required or not a.option_strings):
            continue
        if a.nargs == "?":
            continue
        value = str(next(iter(a.choices))) if a.choices else "x"
        out += [*a.option_strings[:1], value]
    return out


def _is_number(action: argparse.Action) -> bool:
    return getattr(action.type, "__name__", "") in ("int", "float")


def _numeric_options() -> list[tuple[tuple[str, ...], argparse.Action, list[str]]]:
    found = []
    for words, parser in _commands(build_parser()):
        for action in parser._actions:
            if action.option_strings and _is_number(action):
                found.append((words, action, _required(parser, action)))
    return found


NUMERIC = _numeric_options()
# (command, option, its required arguments, value); an option of two values (power --words) gets the values
# without a leading "-", which argparse would take for an option
CASES = [
    (words, action, required, value)
    for words, action, required in NUMERIC
    for value in NON_FINITE
    if action.nargs in (None, "?") or not value.startswith("-")
]


def test_the_numeric_options_were_found():
    """Else the test below checks nothing: the options the issue names are among those found."""
    flags = {(" ".join(words), a.option_strings[0]) for words, a, _ in NUMERIC}
    assert {("score", "--threshold"), ("run", "--timeout"), ("run", "--k"), ("power", "--alpha")} <= flags
    assert ("power", "--words") in flags and len(flags) >= 20


@pytest.mark.parametrize(
    ("words", "action", "required", "value"),
    CASES,
    ids=[f"{' '.join(w)} {a.option_strings[0]}={v}" for w, a, _, v in CASES],
)
def test_every_numeric_option_refuses_non_finite_values(words, action, required, value, tmp_path, monkeypatch, figures):
    flag = action.option_strings[0]
    # "=": argparse would take "-inf" alone for an option
    one = action.nargs in (None, "?")
    given = [f"{flag}={value}"] if one else [flag, *(["1"] * (action.nargs - 1)), value]
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)  # a command that took the value would write its default folders (runs/) here
    proc = cli_in_process([*words, *required, *given], env={"VLMPROPRIO_CACHE": str(work / "cache")})
    assert_one_line_error(proc, flag, "finite")
    assert list(work.iterdir()) == [], "the command wrote something before it refused the value"
    figures("non-finite numbers: options", cases=1, refused_in_one_line=1, tracebacks=0)


@pytest.mark.parametrize("value", NON_FINITE)
def test_the_workers_variable_refuses_non_finite_values(value, tmp_path, monkeypatch, figures):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "run"
    proc = cli_in_process(
        ["run", "--model", "reference", "--episodes", "door_00", "--conditions", "none", "--out", out],
        env={"VLMPROPRIO_WORKERS": value, "VLMPROPRIO_CACHE": str(tmp_path / "cache")},
    )
    assert_one_line_error(proc, "$VLMPROPRIO_WORKERS", repr(value))
    assert not out.exists()
    figures("non-finite numbers: environment", cases=1, refused_in_one_line=1, tracebacks=0)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_range_check_refuses_non_finite_values(value):
    """check_range, which every command's range checks use, refuses them too (the Python API's callers)."""
    from vlmproprio.errors import UsageError
    from vlmproprio.options import check_range

    with pytest.raises(UsageError, match="--threshold must be a finite number"):
        check_range("--threshold", float(value), 0.0, 1.0)
    with pytest.raises(UsageError, match="--limit must be a finite number"):
        check_range("--limit", float(value), 1)


def test_finite_values_still_parse():
    args = build_parser().parse_args(["score", "RUN", "--threshold", "0.5"])
    assert args.threshold == 0.5
    args = build_parser().parse_args(["run", "--model", "reference", "--k", "3", "--timeout", "2.5"])
    assert (args.k, args.timeout) == (3, 2.5)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "--model", "reference", "--k", "1.5"])  # not a whole number


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_score_settings_refuse_non_finite_thresholds(value):
    """The scoring settings every front door builds (CLI, Python API, inspect and lmms-eval tasks) refuse them."""
    from vlmproprio.errors import UsageError
    from vlmproprio.evaluation.definitions import ScoreSettings

    with pytest.raises(UsageError, match="threshold must be a finite number"):
        ScoreSettings(threshold=float(value))
    with pytest.raises(UsageError, match="thresholds must be a finite number"):
        ScoreSettings(thresholds=(0.5, float(value)))
