"""Issue 36, items 15 and 17: start-up, closed pipes, and messages that said something wrong or unclear.

* A reader that leaves (``vlmproprio models | head -c 1``) ends the command quietly, exit 0, whenever the pipe
  breaks (the handler set stdout to None, then flushed it). Ctrl-C at any moment of start-up is one line and exit
  130, never a traceback through vlmproprio's modules.
* Every path option and argument refuses an empty value (``--out ''`` ran into the current folder); a name with
  a control character cannot split an error line; errors name the server ``$OPENAI_BASE_URL`` points at; a
  ``--fixtures`` folder that is not there is an error for ``models`` too; a 429 whose Retry-After the SDK would
  not wait for does not claim "5 tries"; a symbolic link in a fixture folder gets one answer from ``manifest``,
  ``verify`` and ``run``; an ``episode.json`` field of the wrong JSON type is named, not a Python error; ``score``
  with a read-only cache folder works when the sidecars hold every vector.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fault_support import cli_in_process
from reliability_support import (
    REPO,
    assert_argparse_error,
    assert_one_line_error,
    caption_responder,
    cli,
    cli_command,
    cli_env,
    fixture_subset,
)
from test_write_failures import FAIL_PRELUDE

from vlmproprio.episodes import write_manifest
from vlmproprio.testing.openai_server import FakeOpenAIServer, request_digest

RUN = ("--model", "reference", "--episodes", "door_00", "--conditions", "none", "--no-progress")


@pytest.fixture
def fixtures(tmp_path) -> Path:
    return fixture_subset(tmp_path / "fixtures", ["door_00"])


# ---------------------------------------------------------------------------------------------- item 15


@pytest.mark.parametrize("argv", [["models"], ["models", "--plain"], ["--help"], ["run", "--help"]], ids=" ".join)
def test_a_reader_that_left_ends_the_command_quietly(argv, figures):
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the first byte: every write meets a broken pipe
    try:
        proc = subprocess.run(
            cli_command(argv), stdout=write, stderr=subprocess.PIPE, text=True, env=cli_env(), timeout=120
        )
    finally:
        os.close(write)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # no traceback, no "Exception ignored ... BrokenPipeError"
    figures("closed pipes (issue 36: 15)", commands=1, quiet_exits=1, tracebacks=0)


def test_a_broken_pipe_that_is_not_stdout_is_an_error_not_a_quiet_end(figures):
    """A socket or a library's pipe that breaks is a failure: only stdout's reader leaving ends quietly."""
    prelude = (
        "import vlmproprio.cli.models as m\n"
        "def broken(args):\n    raise BrokenPipeError(32, 'Broken pipe')\n"
        "m.cmd_models = broken"
    )
    assert_one_line_error(cli(["models"], python_prelude=prelude), "Broken pipe")
    figures("closed pipes (issue 36: 15)", commands=1, quiet_exits=0, tracebacks=0)


# Frames of a traceback that went through vlmproprio's code (its package __init__ installs the handler: the few
# instructions before that are the interpreter's start-up, as are the frozen importlib frames before it runs).
OUR_FRAME = re.compile(r'File "[^"]*vlmproprio/(?!__init__\.py")[^"]*"')


def test_ctrl_c_at_any_moment_of_start_up_is_one_line(tmp_path, figures):
    outcomes = {"one_line": 0, "before_python": 0, "in_python_start_up": 0, "finished": 0}
    for i in range(40):
        proc = subprocess.Popen(
            cli_command(["models"]), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=cli_env()
        )
        time.sleep(i * 0.01)  # 0 to 0.4 s: the interpreter's start and the import of every command module
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
        if err.strip() == "vlmproprio: interrupted":
            # 130, or killed by SIGINT (what a shell also shows as 130): CPython ends that way once an interrupt
            # has gone through some extension's initialisation, even one that was caught
            assert proc.returncode in (130, -signal.SIGINT), proc.returncode
            outcomes["one_line"] += 1
        elif proc.returncode == 0:
            outcomes["finished"] += 1
        elif "Traceback" in err:  # the interpreter's own start-up, before any line of vlmproprio ran
            assert not OUR_FRAME.search(err), err
            outcomes["in_python_start_up"] += 1
        else:
            assert proc.returncode == -signal.SIGINT and err == "", (proc.returncode, err)
            outcomes["before_python"] += 1
    assert outcomes["one_line"] >= 10, outcomes  # the window that mattered was hit, many times
    figures(
        "Ctrl-C during start-up (issue 36: 15)", interrupts=40, **{k.replace(" ", "_"): v for k, v in outcomes.items()}
    )


# ---------------------------------------------------------------------------------------------- item 17


EMPTY_PATHS = {
    "run --out": ["run", *RUN, "--out", ""],
    "run --cache-dir": ["run", *RUN, "--cache-dir", ""],
    "run --fixtures": ["run", *RUN, "--fixtures", ""],
    "score RUN_DIR": ["score", ""],
    "score --encoder": ["score", "somewhere", "--encoder", ""],
    "report RUN_DIR": ["report", ""],
    "report --out": ["report", "somewhere", "--out", ""],
    "cassette import": ["cassette", "import", ""],
    "cassette export --out": ["cassette", "export", "--model", "reference", "--out", ""],
    "compare --out": ["compare", "a", "b", "--out", ""],
    "verify --fixtures": ["verify", "--fixtures", " "],
}


@pytest.mark.parametrize("case", list(EMPTY_PATHS))
def test_an_empty_path_is_refused_not_read_as_the_current_folder(tmp_path, fixtures, case, figures):
    work = tmp_path / "work"
    work.mkdir()
    proc = cli(EMPTY_PATHS[case], cwd=work, env=cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache")))
    assert_argparse_error(proc, "an empty")
    assert list(work.iterdir()) == []
    figures("empty paths (issue 36: 17)", cases=1, usage_errors=1, files_written=0)


def _benchmark(*options: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "pytest", "benchmark/", "-q", "-p", "no:cacheprovider", "--co", *options],
        cwd=REPO, env=cli_env(), capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


@pytest.mark.parametrize("flag", ["--run-dir", "--bench-fixtures"])
def test_an_empty_path_is_a_usage_error_of_the_benchmark_plugin(flag, figures):
    proc = _benchmark(flag, "")
    out = proc.stdout + proc.stderr
    assert proc.returncode == 4, out  # pytest's usage error
    assert "an empty path" in out and "Traceback" not in out
    figures("empty paths (issue 36: 17)", cases=1, usage_errors=1, files_written=0)


def test_the_benchmark_plugin_escapes_control_characters_in_its_usage_error(figures):
    proc = _benchmark("--episodes", "door_00\nx")
    assert proc.returncode == 4, proc.stdout + proc.stderr
    (line,) = [line for line in (proc.stdout + proc.stderr).splitlines() if "unknown episode" in line]
    assert "door_00\\nx (did you mean" in line
    figures("control characters in error lines (issue 36: 17)", cases=1, one_line_errors=1)


CONTROL = {
    "newline in an episode id": (["run", *RUN[:2], "--episodes", "door_00\nx", "--conditions", "none"], "door_00\\nx"),
    "escape in an episode id": (["run", *RUN[:2], "--episodes", "door\x1b[2J", "--conditions", "none"], "door\\x1b[2J"),
    "newline in --fixtures": (["verify", "--fixtures", "no\nwhere"], "no\\nwhere"),
    "line separator in a cassette path": (["cassette", "import", "a\u2028b.jsonl"], "a\\u2028b.jsonl"),
}


@pytest.mark.parametrize("case", list(CONTROL))
def test_control_characters_in_names_are_escaped_in_the_error_line(fixtures, tmp_path, case, figures):
    argv, escaped = CONTROL[case]
    if argv[0] == "run":
        argv = [*argv, "--fixtures", str(fixtures), "--out", str(tmp_path / "run")]
    proc = cli(argv, cwd=tmp_path, env=cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache")))
    line = assert_one_line_error(proc, escaped)
    assert not any(c in proc.stderr for c in "\x1b\u2028")
    assert line
    figures("control characters in error lines (issue 36: 17)", cases=1, one_line_errors=1)


def _openai_run(fixtures: Path, out: Path, *extra: str) -> list[str]:
    return ["run", "--model", "openai:m", "--episodes", "door_00", "--conditions", "none", "--fixtures", fixtures,
            "--no-progress", "--concurrency", "1", "--out", out, "--cache-dir", out.parent / "cache", *extra]  # fmt: skip


def test_errors_name_the_server_openai_base_url_points_at(fixtures, tmp_path, figures):
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject("429", times=100, retry_after=100_000)  # not retried: one request, a fast failure
        env = {"OPENAI_BASE_URL": server.base_url, "OPENAI_API_KEY": "sk-test-0123456789abcdef"}
        proc = cli_in_process(_openai_run(fixtures, tmp_path / "run"), env=env)
    line = assert_one_line_error(proc, server.base_url, "HTTP 429")
    assert "OpenAI API" not in line
    figures("server named in errors (issue 36: 17)", cases=1, named=1)


@pytest.mark.parametrize(("fault", "wait"), [("429", 100_000), ("429", 121), ("500", 3600)])
def test_a_response_the_sdk_does_not_retry_is_not_called_five_tries(fixtures, tmp_path, fault, wait, figures):
    """The SDK gives up at once on a Retry-After longer than it waits (120 s): one request was sent."""
    with FakeOpenAIServer(responder=caption_responder) as server:
        server.inject(fault, times=100, retry_after=wait)
        proc = cli_in_process(_openai_run(fixtures, tmp_path / "run", "--base-url", server.base_url))
        bodies = [request_digest(r.body) for r in server.chat_requests]
    line = assert_one_line_error(proc, f"HTTP {fault}, not retried", f"Retry-After asks to wait {wait} s")
    assert "tries" not in line
    assert len(set(bodies)) == len(bodies) >= 1  # each request sent once (a worker may start the next one)
    figures("tries counted (issue 36: 17)", cases=1, requests_sent=len(bodies), tries_claimed=0)


@pytest.mark.parametrize("how", ["--fixtures", "VLMPROPRIO_FIXTURES"])
def test_models_with_a_fixture_folder_that_is_not_there_fails(tmp_path, how, figures):
    missing = str(tmp_path / "nonexistent")
    env = cli_env(**({"VLMPROPRIO_FIXTURES": missing} if how != "--fixtures" else {}))
    proc = cli(["models", *(["--fixtures", missing] if how == "--fixtures" else [])], env=env)
    assert_one_line_error(proc, missing, "does not exist")
    figures("fixture folders that are not there (issue 36: 17)", cases=1, one_line_errors=1)


def _linked_episode(tmp_path: Path) -> tuple[Path, Path]:
    fx = fixture_subset(tmp_path / "fixtures", ["door_00", "door_01"])
    elsewhere = tmp_path / "elsewhere" / "door_00"
    shutil.move(fx / "episodes" / "door_00", elsewhere)
    (fx / "episodes" / "door_00").symlink_to(elsewhere, target_is_directory=True)
    return fx, fx / "episodes" / "door_00"


def _linked_frame(tmp_path: Path) -> tuple[Path, Path]:
    fx = fixture_subset(tmp_path / "fixtures", ["door_00"])
    frame = fx / "episodes/door_00/frames/000.png"
    (tmp_path / "elsewhere").mkdir()
    shutil.move(frame, tmp_path / "elsewhere" / "000.png")
    frame.symlink_to(tmp_path / "elsewhere" / "000.png")
    return fx, frame


@pytest.mark.parametrize("link", [_linked_episode, _linked_frame], ids=["episode folder", "frame"])
def test_a_symbolic_link_in_the_fixtures_gets_one_answer_from_manifest_verify_and_run(tmp_path, link, figures):
    fixtures, linked = link(tmp_path)
    for command in ("manifest", "verify", "run"):
        if command != "manifest":  # verify and run check the fixtures against a manifest of the real files
            write_manifest_of_real_files(fixtures)
        args = [command, "--fixtures", fixtures]
        if command == "run":
            args += ["--model", "reference", "--conditions", "none", "--no-progress", "--out", tmp_path / "run"]
        proc = cli([str(a) for a in args], env=cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache")))
        assert_one_line_error(proc, f"{linked}: a symbolic link")
    figures("symbolic links in fixtures (issue 36: 17)", cases=1, commands_agreeing=3)


def write_manifest_of_real_files(root: Path) -> None:
    """The manifest of the files under ``root`` that are not links (rglob does not enter a linked folder)."""
    from vlmproprio.episodes.types import FORMAT_VERSION
    from vlmproprio.io import sha256_file

    files = {
        p.relative_to(root).as_posix(): sha256_file(p)
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.is_symlink() and p.name != "manifest.json"
    }
    (root / "manifest.json").write_text(json.dumps({"format_version": FORMAT_VERSION, "files": files}, indent=1))


WRONG_TYPES = {
    "target_bin a string": (lambda d: d.update(target_bin="far right"), "target_bin must be an object"),
    "target_bin index a string": (lambda d: d["target_bin"].update(index="1"), "target_bin: index must be an integer"),
    "target_bin with an unknown key": (lambda d: d["target_bin"].update(colour="red"), "unknown key(s) 'colour'"),
    "a phase a string": (lambda d: d["phases"].__setitem__(0, "approach"), "phases[0] must be an object"),
    "versions a string": (lambda d: d.update(versions="1.5.2"), "versions must be a JSON object"),
    "image_size a number": (lambda d: d.update(image_size=256), "image_size must be a list"),
    "phase_names a string": (lambda d: d.update(phase_names="approach"), "phase_names must be a list"),
    "a frame a list": (lambda d: d["frames"].__setitem__(0, [0, 1]), "frames[0] must be an object"),
    "seed a string": (lambda d: d.update(seed="110"), "seed must be an integer"),
}


@pytest.mark.parametrize("case", list(WRONG_TYPES))
def test_a_field_of_the_wrong_json_type_is_named_not_a_python_error(tmp_path, case, figures):
    edit, message = WRONG_TYPES[case]
    fixtures = fixture_subset(tmp_path / "fixtures", ["bin1_00"])
    path = fixtures / "episodes/bin1_00/episode.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    write_manifest(fixtures)
    args = ["run", "--fixtures", fixtures, "--model", "reference", "--conditions", "none", "--out", tmp_path / "run"]
    proc = cli([str(a) for a in args], env=cli_env(VLMPROPRIO_CACHE=str(tmp_path / "cache")))
    line = assert_one_line_error(proc, "episode.json", message)
    assert not re.search(r"\*\*|TypeError|ValueError|argument after|object is not|sequence element", line), line
    figures("episode.json fields of the wrong type (issue 36: 17)", cases=1, named=1, python_errors=0)


def test_score_with_a_read_only_cache_folder_uses_the_sidecars(tmp_path, figures):
    """Every caption's vector is in the model's sidecar: the cache folder is never needed, so it may be read-only
    (made so inside the CLI's process: CI runs as root, where chmod stops nothing)."""
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    (fixtures / "responses").mkdir()
    shutil.copy(REPO / "fixtures/responses/reference.embeddings.npz", fixtures / "responses")
    write_manifest(fixtures)
    run = tmp_path / "run"
    proc = cli(["run", "--fixtures", str(fixtures), *RUN, "--out", str(run), "--cache-dir", str(tmp_path / "c")])
    assert proc.returncode == 0, proc.stderr
    read_only = tmp_path / "read-only-cache"
    env = cli_env(VP_FAIL_UNDER=str(read_only), VP_FAIL_KIND="readonly")
    proc = cli(["score", str(run), "--cache-dir", str(read_only)], env=env, python_prelude=FAIL_PRELUDE)
    assert proc.returncode == 0, proc.stderr
    assert "0 computed" in proc.stdout and not read_only.exists()
    figures("score with a read-only cache (issue 36: 17)", cases=1, scored=1)
