"""Item 5, bad input at the edges, through the real CLI in processes of its own.

Every case is a user's mistake or a damaged input: unknown or unsafe model names, episode ids with path
separators or '..', missing/extra/damaged episode files, NaN and wrong-shaped states, a truncated PNG,
wrong flag values. Each must end in exactly one ``vlmproprio: error:`` line that says what is wrong, exit
code 2, and no traceback; ``--debug`` must show the traceback. Runs happen in a sandbox (its own cwd, HOME,
TMPDIR, cache root), snapshotted before and after: a refused run touches nothing at all, and an accepted run
with an odd model name writes only inside its run and cache directories. Those snapshotted runs are fresh
interpreters; the others, which check exit codes and error lines, are forked from an import-once server.

The pytest plugin's options (``pytest benchmark/ --model nope`` ...) are usage errors (exit 4), not crashes.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from fast_support import forked_cli
from reliability_support import (
    REPO,
    assert_argparse_error,
    assert_one_line_error,
    caption_responder,
    changed_paths,
    cli,
    cli_env,
    fixture_subset,
    tree_snapshot,
)

from vlmproprio.episodes import write_manifest
from vlmproprio.models import resolve_model
from vlmproprio.testing.openai_server import FakeOpenAIServer


@pytest.fixture(scope="module")
def clean_fixtures(tmp_path_factory) -> Path:
    return fixture_subset(tmp_path_factory.mktemp("bad-input") / "fixtures", ["door_00", "bin1_00"])


@pytest.fixture
def sandbox(tmp_path, clean_fixtures):
    """A folder holding everything a run could reach: fixtures, cwd, HOME, TMPDIR, the cache root."""
    shutil.copytree(clean_fixtures, tmp_path / "fixtures")
    for d in ("work", "home", "tmp"):
        (tmp_path / d).mkdir()
    (tmp_path / "work" / "a-file").write_text("in the way\n")
    env = cli_env(
        HOME=str(tmp_path / "home"),
        TMPDIR=str(tmp_path / "tmp"),
        VLMPROPRIO_HOME=str(tmp_path / "home" / "vlmproprio"),
        VLMPROPRIO_CACHE=str(tmp_path / "work" / "cache-root"),
    )
    env.pop("OPENAI_API_KEY", None)
    return tmp_path, env


def run_in(sandbox, *args: str, debug: bool = False, fresh: bool = False) -> subprocess.CompletedProcess:
    """``vlmproprio run ARGS`` in the sandbox's folder and environment, as a process of its own.

    By default it is forked from the import-once server (fast_support): its own PID, environment, folder and
    whole stdout/stderr, what a check of exit code and error lines needs, without ~0.4 CPU s of imports.
    ``fresh``: a new interpreter, for the tests that snapshot the sandbox: an interpreter that started
    elsewhere may have read HOME or TMPDIR (tempfile's cached folder, a library's config folder) before the
    sandbox's were set, and its files would then land outside the snapshot."""
    root, env = sandbox
    base = ["run", "--fixtures", str(root / "fixtures"), "--no-progress", "--out", "run", "--cache-dir", "cache"]
    argv = (["--debug"] if debug else []) + base + list(args)
    if fresh:
        return cli(argv, cwd=root / "work", env=env)
    return forked_cli(argv, root / "logs", cwd=root / "work", env=env)


def _with_defaults(args: tuple[str, ...]) -> list[str]:
    out = list(args)
    if "--model" not in out:
        out = ["--model", "reference", *out]
    if "--conditions" not in out:
        out += ["--conditions", "none"]
    return out


# ---------------------------------------------------------------------------------------------- names

UNSAFE_MODELS = {
    "nope": "unknown model 'nope'",
    "../evil": "refused",
    "hf:../../evil": "refused",
    "openai:../../evil": "refused",
    "openai:a/../../b": "refused",
    "hf:..\\evil": "refused",
    "tiny-qwen2-vl/../../x": "refused",
    "reference/..": "refused",
    "openai:": "nothing after 'openai:'",
    "hf:": "nothing after 'hf:'",
    "": "empty model name",
    "openai:x\nrm -rf": "control characters",
}
UNSAFE_EPISODES = ["../door_00", "door_00/../../x", "/etc", "..", "door_00/frames", "DOOR_00", "door_00 "]


@pytest.mark.parametrize("name", list(UNSAFE_MODELS), ids=[repr(n) for n in UNSAFE_MODELS])
def test_unknown_and_unsafe_model_names_are_refused_and_touch_nothing(sandbox, name, figures):
    before = tree_snapshot(sandbox[0])
    proc = run_in(sandbox, "--model", name, "--conditions", "none", fresh=True)
    assert_one_line_error(proc, UNSAFE_MODELS[name])
    assert changed_paths(before, tree_snapshot(sandbox[0])) == set()
    figures("bad input: unsafe names", cases=1, refused_in_one_line=1, files_touched=0)


@pytest.mark.parametrize("episode", UNSAFE_EPISODES)
def test_episode_ids_with_path_parts_are_refused_and_touch_nothing(sandbox, episode, figures):
    before = tree_snapshot(sandbox[0])
    proc = run_in(sandbox, "--model", "reference", "--conditions", "none", "--episodes", episode, fresh=True)
    assert_one_line_error(proc, "unknown episode(s)", episode)
    assert changed_paths(before, tree_snapshot(sandbox[0])) == set()
    figures("bad input: unsafe names", cases=1, refused_in_one_line=1, files_touched=0)


def test_an_odd_but_valid_model_name_writes_only_into_run_and_cache(sandbox):
    pytest.importorskip("openai", reason="the openai backend needs the openai SDK")
    root, _ = sandbox
    before = tree_snapshot(root)
    with FakeOpenAIServer(responder=caption_responder) as server:
        proc = run_in(
            sandbox, "--model", "openai:org/model:v1", "--base-url", server.base_url,
            "--episodes", "door_00", "--conditions", "none", "--frame-stride", "3", fresh=True,
        )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    changed = changed_paths(before, tree_snapshot(root))
    assert changed and all(p.startswith(("work/run/", "work/cache/")) for p in changed), sorted(changed)
    slug = resolve_model("openai:org/model:v1").slug  # lossy readable part: a digest suffix keeps it unique
    assert slug.startswith("openai_org_model_v1-")
    assert (root / "work" / "run" / "transcripts" / slug / "door_00__none.json").is_file()


# ---------------------------------------------------------------------------------------------- damaged fixtures


def _episode_json(root: Path, episode: str = "door_00") -> tuple[Path, dict]:
    path = root / "fixtures" / "episodes" / episode / "episode.json"
    return path, json.loads(path.read_text())


def _edit_frames(root: Path, **row) -> None:
    path, meta = _episode_json(root)
    meta["frames"][3].update(row)
    path.write_text(json.dumps(meta))


def _truncate_png(root: Path) -> None:
    png = root / "fixtures" / "episodes" / "door_00" / "frames" / "004.png"
    png.write_bytes(png.read_bytes()[:3000])


# name -> (damage, rewrite the manifest afterwards (the damage is 'blessed'), what the error must say)
DAMAGE = {
    "missing frame": (lambda r: (r / "fixtures/episodes/door_00/frames/003.png").unlink(), False, "003.png: missing"),
    "extra file": (lambda r: (r / "fixtures/episodes/door_00/notes.txt").write_text("x"), False, "notes.txt: extra"),
    "extra episode": (
        lambda r: shutil.copytree(r / "fixtures/episodes/door_00", r / "fixtures/episodes/door_99"),
        False,
        "door_99: extra episode",
    ),
    "truncated png": (_truncate_png, False, "004.png: sha256 differs"),
    "truncated png, manifest rewritten": (_truncate_png, True, "004.png: not a complete PNG"),
    "NaN joints": (lambda r: _edit_frames(r, joints=[float("nan")] * 8), True, "non-finite"),
    "infinite ee": (lambda r: _edit_frames(r, ee=[1e999] * 6), True, "non-finite"),
    "ee of 5 numbers": (lambda r: _edit_frames(r, ee=[0.0] * 5), True, "ee must be a list of 6"),
    "joints 8x2": (lambda r: _edit_frames(r, joints=[[0.0, 0.0]] * 8), True, "non-numeric"),
    "joints a string": (lambda r: _edit_frames(r, joints="0,0,0,0,0,0,0,0"), True, "joints must be a list of 8"),
    "frame path escapes": (lambda r: _edit_frames(r, file="../../../../home/x.png"), True, "leaves the episode folder"),
    "episode.json not JSON": (
        lambda r: (r / "fixtures/episodes/door_00/episode.json").write_text('{"frames": ['),
        True,
        "cannot read episode metadata",
    ),
    "manifest missing": (lambda r: (r / "fixtures/manifest.json").unlink(), False, "manifest missing"),
    "manifest not JSON": (lambda r: (r / "fixtures/manifest.json").write_text("{"), False, "not a valid manifest"),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_episodes_are_one_clear_line(sandbox, case, figures):
    root, _ = sandbox
    damage, bless, message = DAMAGE[case]
    damage(root)
    if bless:
        write_manifest(root / "fixtures")
    proc = run_in(sandbox, "--model", "reference", "--conditions", "none")
    assert_one_line_error(proc, str(root / "fixtures"), message)  # names the file or folder, says what is wrong
    figures("bad input: damaged fixtures", cases=1, one_line_errors=1, tracebacks=0)


# ---------------------------------------------------------------------------------------------- flags

BAD_FLAGS = {
    "unknown condition": (("--conditions", "nope"), "unknown condition 'nope'"),
    "no condition": (("--conditions", ","), "no condition given"),
    "k of 0": (("--k", "0"), "--k must be in [1, inf], got 0"),
    "negative stride": (("--frame-stride", "-1"), "--frame-stride must be in [1, inf], got -1"),
    "zero tokens": (("--max-new-tokens", "0"), "--max-new-tokens must be at least 1"),
    "negative image cap": (("--max-images-p3", "-1"), "--max-images-p3 must be in [0, inf], got -1"),
    "out is a file": (("--out", "a-file"), "cannot create run directory a-file"),
    "cache is a file": (("--cache-dir", "a-file"), "cannot create cache directory a-file"),
    "no fixtures": (("--fixtures", "nowhere"), "--fixtures nowhere: does not exist"),
    "openai without key or server": (("--model", "openai:gpt-x"), "no API key"),
    "negative timeout": (
        ("--model", "openai:gpt-x", "--base-url", "http://127.0.0.1:9/v1", "--timeout", "-1"),
        "timeout must be a positive number",
    ),
    "zero concurrency": (
        ("--model", "openai:gpt-x", "--base-url", "http://127.0.0.1:9/v1", "--concurrency", "0"),
        "concurrency must be >= 1",
    ),
    "bad key variable": (
        ("--model", "openai:gpt-x", "--base-url", "http://127.0.0.1:9/v1", "--api-key-env", "A B"),
        "api_key_env must be an environment variable name",
    ),
    "replay without a cassette": (("--model", "openai:gpt-x", "--mode", "replay"), "no cassette for model"),
}


@pytest.mark.parametrize("case", list(BAD_FLAGS))
def test_wrong_flag_values_are_one_clear_line(sandbox, case, figures):
    args, message = BAD_FLAGS[case]
    proc = run_in(sandbox, *_with_defaults(args))
    assert_one_line_error(proc, message)
    figures("bad input: flags and commands", cases=1, one_line_errors=1, tracebacks=0)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--mode", "fast"), "argument --mode: invalid choice: 'fast'"),
        (("--k", "five"), "argument --k: invalid int value: 'five'"),
        (("--timeout", "soon"), "argument --timeout: invalid float value"),
    ],
)
def test_flags_argparse_refuses_are_its_usage_error(sandbox, args, message):
    assert_argparse_error(run_in(sandbox, "--model", "reference", *args), message)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["score", "nowhere"], "nowhere"),
        (["cassette", "import", "nowhere.jsonl", "--cache", "cache"], "cannot read cassette"),
        (["cassette", "export", "--model", "hf:../x", "--cache", "cache"], "refused"),
        (["verify", "--fixtures", "nowhere"], "--fixtures nowhere: does not exist"),
    ],
)
def test_other_commands_fail_in_one_line(sandbox, argv, message, figures):
    root, env = sandbox
    assert_one_line_error(forked_cli(argv, root / "logs", cwd=root / "work", env=env), message)
    figures("bad input: flags and commands", cases=1, one_line_errors=1, tracebacks=0)


@pytest.mark.parametrize(
    "args",
    [("--model", "nope"), ("--model", "reference", "--conditions", "nope"), ("--model", "reference", "--k", "0")],
)
def test_debug_shows_the_traceback(sandbox, args):
    quiet = run_in(sandbox, *args)
    loud = run_in(sandbox, *args, debug=True)
    assert quiet.returncode == 2 and "Traceback" not in quiet.stderr
    assert loud.returncode != 0 and "Traceback (most recent call last)" in loud.stderr


def test_debug_shows_the_traceback_of_damaged_fixtures(sandbox):
    _edit_frames(sandbox[0], joints=[float("nan")] * 8)
    write_manifest(sandbox[0] / "fixtures")
    assert_one_line_error(run_in(sandbox, "--model", "reference"), "non-finite")
    loud = run_in(sandbox, "--model", "reference", debug=True)
    assert "Traceback (most recent call last)" in loud.stderr and "EpisodeError" in loud.stderr


# ---------------------------------------------------------------------------------------------- the pytest plugin


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--model", "nope"], "unknown model 'nope'"),
        (["--model", "../vlmproprio-no-such-model"], "refused"),  # a relative path pytest cannot find a conftest in
        (["--mode", "fast"], "invalid choice: 'fast'"),
        (["--conditions", "nope"], "unknown condition 'nope'"),
        (["--episodes", "../door_00"], "unknown episode(s) ../door_00"),
        (["--bench-fixtures", "/nowhere"], "--fixtures-dir /nowhere: does not exist"),
    ],
)
def test_benchmark_plugin_options_are_usage_errors(option, message, figures):
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "benchmark/", "-q", "-p", "no:cacheprovider", *option],
        cwd=REPO,
        env=cli_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 4, out  # pytest's "usage error" exit code
    assert "Traceback" not in out and "INTERNALERROR" not in out
    assert message in out
    figures("bad input: pytest plugin options", cases=1, usage_errors=1, crashes=0)
