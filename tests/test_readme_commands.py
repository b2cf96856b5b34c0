"""The README's commands work from a folder other than the repository root, and its promises hold.

* every `vlmproprio ...` line of the README's shell blocks parses (its options exist);
* the command-line section's commands run for real from a temporary folder (fixtures from
  $VLMPROPRIO_FIXTURES), and `verify` / `models` find the fixtures from a subfolder of the repository;
* every `pytest benchmark/ ...` line collects from another folder (`pytest <repo>/benchmark ...`);
* every environment variable vlmproprio reads is in the README's table;
* every command an error message or help text suggests (`vlmproprio ...` in backticks) parses.
"""

from __future__ import annotations

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


def _vp(argv: list[str], cwd: Path, env: dict, timeout: int = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "vlmproprio.cli", *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert proc.returncode == 0, f"vlmproprio {' '.join(argv)} in {cwd}:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    return proc


@pytest.mark.slow
def test_the_command_line_section_runs_from_another_folder(tmp_path: Path) -> None:
    section = README.split("## Command line", 1)[1].split("##", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    commands = [vlmproprio_argv(re.sub(r"\s+#\s.*$", "", x).strip()) for x in block.splitlines() if x.strip()]
    assert commands and all(commands)
    env = _env(tmp_path) | {"VLMPROPRIO_FIXTURES": str(REPO / "fixtures")}
    outputs = [_vp(argv, tmp_path, env).stdout for argv in commands]
    assert outputs[0].startswith("vlmproprio ")
    assert "reference" in outputs[1] and "replay:" in outputs[1]
    assert (tmp_path / "runs" / "try" / "report" / "index.html").is_file()
    assert (tmp_path / "runs" / "try" / "scores" / "frames.csv").is_file()
    assert "match the keys the run recorded, 0 differ" in outputs[-1]


def test_fixtures_are_found_from_a_subfolder_of_the_repository(tmp_path: Path) -> None:
    env = _env(tmp_path)
    out = _vp(["verify"], REPO / "benchmark", env).stdout
    assert "22" in out or "episodes" in out
    models = _vp(["models", "--model", "tiny-qwen2-vl"], REPO / "docs", env).stdout
    assert f"cassette: {REPO / 'fixtures' / 'responses' / 'tiny-qwen2-vl.jsonl'}" in models


def test_outside_any_repository_the_error_says_what_to_do(tmp_path: Path) -> None:
    env = _env(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "vlmproprio.cli", "verify"], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    # the source checkout's fixtures are the last resort (an editable install); a wheel says what to do
    assert proc.returncode == 0 or "pass --fixtures DIR or set VLMPROPRIO_FIXTURES" in proc.stderr


@pytest.mark.parametrize("line", PYTEST_LINES)
def test_every_readme_benchmark_command_collects_from_another_folder(line: str, tmp_path: Path) -> None:
    args = shlex.split(line)[2:]  # after "pytest benchmark/"
    cmd = [sys.executable, "-m", "pytest", str(REPO / "benchmark"), *args, "--collect-only", "-q"]
    env = _env(tmp_path)
    proc = subprocess.run(
        [*cmd, "-p", "no:cacheprovider"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, f"{line}:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}"
    assert "test_counts[" in proc.stdout


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
