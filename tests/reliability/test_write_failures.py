"""Issue 15, defect 4: every write failure is one line naming the path and the cause, exit code 2.

The failures are made where a user meets them: `run`, `record`, `manifest`, `cassette export`, `score`,
`report` and `compare --out` into a read-only folder, a full disk under the run folder, a full SQLite
response cache ("database or disk is full"), and a cache or report folder that is a file. Tests run as root
in CI, where chmod does not stop a write, so read-only folders and a full disk are made inside the CLI's own
process by a prelude that fails the OS calls (EROFS from mkstemp/mkdir under one folder, ENOSPC from fsync
there); the SQLite case is real (the cache database capped with max_page_count), and so are the files in the
way. After each failure: exactly one error line, no traceback, no temporary file left, and every file that
was there before has its old bytes.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from fault_support import cli_in_process
from reliability_support import (
    all_files,
    assert_one_line_error,
    cache_env_sharing_embeddings,
    cli,
    fixture_subset,
    temp_leftovers,
)

RUN_ARGS = ("--model", "reference", "--episodes", "door_00", "--conditions", "none", "--frame-stride", "3")

FAIL_PRELUDE = """
import errno, os, tempfile
FAIL_UNDER, KIND = os.environ["VP_FAIL_UNDER"], os.environ["VP_FAIL_KIND"]
def _under(path):
    return os.path.abspath(str(path)).startswith(FAIL_UNDER)
if KIND == "readonly":
    real_mkstemp, real_mkdir = tempfile.mkstemp, os.mkdir
    def mkstemp(*a, dir=None, **k):
        if dir is not None and _under(dir):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(dir))
        return real_mkstemp(*a, dir=dir, **k)
    def mkdir(path, *a, **k):
        if _under(path):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_mkdir(path, *a, **k)
    tempfile.mkstemp, os.mkdir = mkstemp, mkdir
elif KIND == "full":
    real_fsync = os.fsync
    def fsync(fd):
        if _under(os.readlink(f"/proc/self/fd/{fd}")):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)
    os.fsync = fsync
elif KIND == "sqlite-full":
    import sqlite3
    real_connect = sqlite3.connect
    def connect(path, *a, **k):
        conn = real_connect(path, *a, **k)
        if _under(path):  # no room for one more page: "database or disk is full"
            pages = conn.execute("PRAGMA page_count").fetchone()[0]
            conn.execute(f"PRAGMA max_page_count = {pages}")
        return conn
    sqlite3.connect = connect
"""


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A scored run to fail writes on. Made through the CLI in this process: the failing commands are what is
    checked (they stay subprocesses, with the failure prelude), and scoring in a subprocess imported torch and
    the encoder again (~10 CPU s)."""
    root = tmp_path_factory.mktemp("writes")
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    env = cache_env_sharing_embeddings(root, tmp_path_factory)
    run = root / "run"
    for args in (["run", *RUN_ARGS, "--fixtures", fixtures, "--out", run, "--no-progress"], ["score", run]):
        proc = cli_in_process(args, env={"VLMPROPRIO_CACHE": env["VLMPROPRIO_CACHE"]})
        assert proc.returncode == 0, proc.stderr
    return root, fixtures, run, env


def _case(base, name: str):
    """A fresh copy of the scored run and fixtures for one case, and its own response cache."""
    root, fixtures, run, env = base
    work = root / name
    shutil.copytree(run, work / "run")
    shutil.copytree(fixtures, work / "fixtures")
    shutil.copytree(root / "cache", work / "cache")
    doc = json.loads((work / "run" / "run.json").read_text())
    doc["fixtures"] = str((work / "fixtures").resolve())  # the copy is this run's fixture folder
    (work / "run" / "run.json").write_text(json.dumps(doc, indent=1) + "\n")
    return work, {**env, "VLMPROPRIO_CACHE": str(work / "cache")}


def _snapshot(work: Path) -> dict[str, bytes]:
    # SQLite rewrites its own header and WAL on every open: the databases are checked by their answers elsewhere
    return {p.relative_to(work).as_posix(): p.read_bytes() for p in all_files(work) if "cache.db" not in p.name}


# name -> (command given the case folder, folder whose writes fail, how they fail, what the line names)
CASES = {
    "run --out read-only": (lambda w: ["run", *RUN_ARGS, "--out", w / "run"], "run", "readonly", "run.json"),
    "run, disk full in the run folder": (
        lambda w: ["run", *RUN_ARGS, "--out", w / "run"],
        "run",
        "full",
        "No space left on device",
    ),
    "run, response cache database full": (
        lambda w: ["run", *RUN_ARGS[:-2], "--frame-stride", "2", "--out", w / "run2"],
        "cache",
        "sqlite-full",
        "database or disk is full",
    ),
    "run --mode record, read-only fixtures": (
        lambda w: ["run", *RUN_ARGS, "--out", w / "rec", "--mode", "record"],
        "fixtures/responses",
        "readonly",
        "responses",
    ),
    "manifest, read-only fixtures": (lambda w: ["manifest"], "fixtures", "readonly", "manifest.json"),
    "cassette export --out read-only": (
        lambda w: [
            *("cassette", "export", "--model", "reference"),
            *("--out", w / "ro" / "ref.jsonl"),  # the cache: $VLMPROPRIO_CACHE
        ],
        "ro",
        "readonly",
        "ro",
    ),
    "score, read-only run folder": (lambda w: ["score", w / "run"], "run", "readonly", "run"),
    "report, read-only run folder": (lambda w: ["report", w / "run"], "run/report", "readonly", "report"),
    "compare --out read-only": (
        lambda w: ["compare", w / "run", w / "run", "--out", w / "ro" / "cmp.md"],
        "ro",
        "readonly",
        "cmp.md",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_write_failure_is_one_line_naming_path_and_cause(base, case, figures):
    work, env = _case(base, case.replace(" ", "_").replace(",", "").replace("/", "_"))
    make_args, fail_under, kind, named = CASES[case]
    before = _snapshot(work)
    env = {**env, "VP_FAIL_UNDER": str(work / fail_under), "VP_FAIL_KIND": kind}
    args = [str(a) for a in make_args(work)]
    if args[0] in ("run", "manifest"):
        args += ["--fixtures", str(work / "fixtures")]
    proc = cli(args, cwd=work, env=env, python_prelude=FAIL_PRELUDE)
    line = assert_one_line_error(proc, "cannot ", named)
    assert temp_leftovers(work) == []
    after = _snapshot(work)
    assert {k: v for k, v in after.items() if k in before} == before  # nothing half-written, nothing lost
    figures("write failures", paths=1, one_line_errors=1, tracebacks=0, half_written=0)
    assert len(line) < 600


@pytest.mark.parametrize("what", ["--cache-dir", "report --out"])
def test_a_file_in_the_way_is_one_line(base, what, figures):
    work, env = _case(base, f"file-in-the-way-{what.replace(' ', '_')}")
    blocker = work / "blocker"
    blocker.write_text("a file, not a folder\n")
    if what == "--cache-dir":
        args = ["run", *RUN_ARGS, "--fixtures", work / "fixtures", "--out", work / "run3", "--cache-dir", blocker]
    else:
        args = ["report", work / "run", "--out", blocker / "report"]
    proc = cli(args, cwd=work, env=env)
    assert_one_line_error(proc, str(blocker))
    assert blocker.read_text() == "a file, not a folder\n"
    figures("write failures", paths=1, one_line_errors=1, tracebacks=0, half_written=0)
