"""The README's commands work from a folder other than the repository root, and its promises hold.

* every `vlmproprio ...` line of the README's shell blocks parses (its options exist);
* the command-line section's commands run for real from a temporary folder (fixtures from
  $VLMPROPRIO_FIXTURES), and `verify` / `models` find the fixtures from a subfolder of the repository;
* every `pytest benchmark/ ...` line collects from another folder (`pytest <repo>/benchmark ...`);
* every environment variable vlmproprio reads is in the README's table;
* every command an error message or help text suggests (`vlmproprio ...` in backticks) parses.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from vlmproprio.cli import build_parser
from vlmproprio.locations import ENVIRONMENT

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
SRC = REPO / "src" / "vlmproprio"


def shell_lines() -> list[str]:
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", README, flags=re.S):
        block = re.sub(r"\\\n\s*", " ", block)  # a command continued with a backslash is one line
        for line in block.splitlines():
            line = re.sub(r"\s+#\s.*$", "", line).strip().rstrip("&").strip()
            if line and not line.startswith("#"):
                lines.extend(part.strip() for part in line.split("&&"))
    return lines


def vlmproprio_argv(line: str) -> list[str] | None:
    words = shlex.split(line)
    while words and re.fullmatch(r"[A-Z_]+=.*", words[0]):  # VAR=value prefixes
        words = words[1:]
    if words and words[0].endswith("vlmproprio"):
        return words[1:]
    return None


VLMPROPRIO_LINES = [line for line in shell_lines() if vlmproprio_argv(line) is not None]
PYTEST_LINES = [line for line in shell_lines() if line.startswith("pytest benchmark/")]


def test_the_readme_has_commands() -> None:
    assert len(VLMPROPRIO_LINES) >= 15 and len(PYTEST_LINES) >= 4


@pytest.mark.parametrize("line", VLMPROPRIO_LINES)
def test_every_readme_vlmproprio_command_parses(line: str) -> None:
    argv = vlmproprio_argv(line)
    if argv == ["--version"]:
        return  # argparse's version action exits; it runs for real below
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"README command does not parse ({exc.code}): {line}")


def _env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("VLMPROPRIO_")}
    env |= {"VLMPROPRIO_CACHE": os.environ["VLMPROPRIO_CACHE"], "PYTHONPATH": str(REPO / "src")}
    return env


# One child process runs several commands in turn (each in its own working folder, with the child's clean
# environment), so that the interpreter start and the imports are paid once, not once per command: what these
# tests check is the working folder and the environment, which the child gives each command as a process would.
_BATCH = """
import contextlib, io, json, os, sys
results = []
for cwd, argv in json.loads(sys.argv[1]):
    os.chdir(cwd)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = MAIN(argv)
        except SystemExit as exc:  # argparse's --version and usage errors exit
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    results.append([code, out.getvalue(), err.getvalue()])
print(json.dumps(results))
"""
VLMPROPRIO_MAIN = "from vlmproprio.cli import main as MAIN\n"
PYTEST_MAIN = "from pytest import main as MAIN\n"


def _batch(main: str, commands: list[tuple[Path, list[str]]], env: dict) -> list[tuple[int, str, str]]:
    """``(exit code, stdout, stderr)`` of each ``(working folder, argv)`` run by ``main`` in one child process."""
    payload = json.dumps([[str(cwd), argv] for cwd, argv in commands])
    proc = subprocess.run(
        [sys.executable, "-c", main + _BATCH, payload],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, f"{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return [tuple(r) for r in json.loads(proc.stdout.strip().splitlines()[-1])]


def _vps(commands: list[tuple[Path, list[str]]], env: dict) -> list[str]:
    """The standard output of each ``vlmproprio`` command, all run in one child; each must succeed."""
    results = _batch(VLMPROPRIO_MAIN, commands, env)
    for (cwd, argv), (code, out, err) in zip(commands, results, strict=True):
        assert code == 0, f"vlmproprio {' '.join(argv)} in {cwd}:\n{out[-2000:]}\n{err[-2000:]}"
    return [out for _, out, _ in results]


@pytest.mark.slow
def test_the_command_line_section_runs_from_another_folder(tmp_path: Path) -> None:
    section = README.split("## Command line", 1)[1].split("##", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    commands = [vlmproprio_argv(re.sub(r"\s+#\s.*$", "", x).strip()) for x in block.splitlines() if x.strip()]
    assert commands and all(commands)
    env = _env(tmp_path) | {"VLMPROPRIO_FIXTURES": str(REPO / "fixtures")}
    outputs = _vps([(tmp_path, argv) for argv in commands], env)
    assert outputs[0].startswith("vlmproprio ")
    assert "reference" in outputs[1] and "replay:" in outputs[1]
    assert (tmp_path / "runs" / "try" / "report" / "index.html").is_file()
    assert (tmp_path / "runs" / "try" / "scores" / "frames.csv").is_file()
    assert "match the keys the run recorded, 0 differ" in outputs[-1]


@pytest.fixture(scope="module")
def located(tmp_path_factory) -> list[tuple[int, str, str]]:
    """``verify`` from a folder outside any repository (first: nothing an earlier command did can help it), then
    ``verify`` from benchmark/ and ``models`` from docs/, all in one child (one interpreter start and one import
    of vlmproprio for the three, not two children): (exit code, stdout, stderr) of each."""
    outside = tmp_path_factory.mktemp("outside")
    commands = [
        (outside, ["verify"]),
        (REPO / "benchmark", ["verify"]),
        (REPO / "docs", ["models", "--model", "tiny-qwen2-vl"]),
    ]
    return _batch(VLMPROPRIO_MAIN, commands, _env(outside))


def test_fixtures_are_found_from_a_subfolder_of_the_repository(located) -> None:
    for code, out, err in located[1:]:
        assert code == 0, f"{out[-2000:]}\n{err[-2000:]}"
    (_, out, _), (_, models, _) = located[1:]
    assert "22" in out or "episodes" in out
    assert f"cassette: {REPO / 'fixtures' / 'responses' / 'tiny-qwen2-vl.jsonl'}" in models


def test_outside_any_repository_the_error_says_what_to_do(located) -> None:
    code, _, err = located[0]
    # the source checkout's fixtures are the last resort (an editable install); a wheel says what to do
    assert code == 0 or "pass --fixtures DIR or set VLMPROPRIO_FIXTURES" in err


@pytest.fixture(scope="module")
def collected(tmp_path_factory) -> dict[str, tuple[int, str, str]]:
    """Every README ``pytest benchmark/ ...`` line collected from a temporary folder (``pytest <repo>/benchmark
    ...``), all in one child process (one ``pytest.main`` per line): the line -> (exit code, stdout, stderr)."""
    where = tmp_path_factory.mktemp("collect")
    argvs = [
        [str(REPO / "benchmark"), *shlex.split(line)[2:], "--collect-only", "-q", "-p", "no:cacheprovider"]
        for line in PYTEST_LINES
    ]  # after "pytest benchmark/"
    return dict(zip(PYTEST_LINES, _batch(PYTEST_MAIN, [(where, a) for a in argvs], _env(where)), strict=True))


@pytest.mark.parametrize("line", PYTEST_LINES)
def test_every_readme_benchmark_command_collects_from_another_folder(line: str, collected) -> None:
    code, out, err = collected[line]
    assert code == 0, f"{line}:\n{out[-2000:]}\n{err[-2000:]}"
    assert "test_counts[" in out


def test_every_environment_variable_read_is_in_the_readme() -> None:
    table = README.split("Environment variables read by vlmproprio", 1)[1].split("\n\n", 2)[1]
    read = set(ENVIRONMENT)
    for path in SRC.rglob("*.py"):
        text = path.read_text()
        read |= set(re.findall(r"environ(?:\.get|\.setdefault)?\(\s*\"([A-Z][A-Z0-9_]+)\"", text))
        read |= set(re.findall(r"environ\[\s*\"([A-Z][A-Z0-9_]+)\"\s*\]", text))
    read -= {"PYOPENGL_PLATFORM"}  # derived from MUJOCO_GL, never read from the user
    missing = sorted(v for v in read if f"`{v}`" not in table)
    assert not missing, f"environment variables read but not in the README's table: {missing}"


def _suggested_commands() -> list[tuple[str, str]]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        for cmd in re.findall(r"`(vlmproprio [^`]+)`", path.read_text()):
            found.append((path.relative_to(SRC).as_posix(), cmd))
    return found


@pytest.mark.parametrize(("where", "command"), _suggested_commands())
def test_every_suggested_command_parses(where: str, command: str) -> None:
    text = re.sub(r"\{[^}]*\}", "x", command)  # f-string fields become a value
    argv = shlex.split(text)[1:]
    if argv in (["--help"], ["--version"]):
        return
    try:
        build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{where} suggests `{command}`, which the CLI rejects")
