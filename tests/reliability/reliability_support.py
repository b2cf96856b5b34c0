"""Shared helpers for the reliability suite: the real CLI in a subprocess, fixture copies, run snapshots.

Every guarantee of docs/reliability.md is one ``test_*.py`` module next to this file; what they share lives here so that each
module reads as the guarantee it checks.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.cache import ResponseCache
from vlmproprio.episodes import write_manifest
from vlmproprio.testing.openai_server import request_digest

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "fixtures"
ERROR_PREFIX = "vlmproprio: error: "


# ---------------------------------------------------------------------------------------------- fixtures


def fixture_subset(dest: Path, episode_ids: Sequence[str]) -> Path:
    """A fixture set holding copies of the real episodes ``episode_ids``, with its own manifest.

    Runs load (and verify) every episode of their fixture set; a small set keeps a subprocess run short."""
    for eid in episode_ids:
        shutil.copytree(FIXTURES / "episodes" / eid, dest / "episodes" / eid)
    write_manifest(dest)
    return dest


def fixture_copy(dest: Path) -> Path:
    """A full copy of the shipped fixtures (manifest included), safe to damage."""
    shutil.copytree(FIXTURES, dest)
    return dest


# ---------------------------------------------------------------------------------------------- the CLI


def cli_env(**extra: str) -> dict[str, str]:
    """The environment for a CLI subprocess: this checkout's code first, offline, one thread."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "OMP_NUM_THREADS": "1"}
    env.update(extra)
    return env


def cli_command(args: Sequence[str], *, python_prelude: str | None = None) -> list[str]:
    """``python -m vlmproprio.cli ARGS``; with a prelude, that code runs first in the same interpreter."""
    if python_prelude is None:
        return [sys.executable, "-m", "vlmproprio.cli", *args]
    code = python_prelude + "\nimport sys\nfrom vlmproprio.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    return [sys.executable, "-c", code, *args]


def cli(
    args: Sequence[str],
    *,
    cwd: Path | None = None,
    env: dict[str, str] | None = None,
    timeout: float = 120,
    python_prelude: str | None = None,
) -> subprocess.CompletedProcess:
    return subprocess.run(
        cli_command([str(a) for a in args], python_prelude=python_prelude),
        cwd=cwd or REPO,
        env=env or cli_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def assert_one_line_error(proc: subprocess.CompletedProcess, *must_contain: str) -> str:
    """The CLI failed with exit code 2 and exactly one ``vlmproprio: error:`` line on stderr, no traceback."""
    err_lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, f"exit {proc.returncode}, stderr:\n{proc.stderr}"
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout, proc.stderr
    errors = [line for line in err_lines if line.startswith(ERROR_PREFIX)]
    assert len(errors) == 1, f"expected one error line, got:\n{proc.stderr}"
    (line,) = errors
    for part in must_contain:
        assert part in line, f"{part!r} not in {line!r}"
    return line


def assert_argparse_error(proc: subprocess.CompletedProcess, *must_contain: str) -> str:
    """argparse's own refusal: exit code 2, its usage line and one ``error:`` line, no traceback."""
    assert proc.returncode == 2, f"exit {proc.returncode}, stderr:\n{proc.stderr}"
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if ": error: " in line]
    assert len(errors) == 1, proc.stderr
    for part in must_contain:
        assert part in errors[0], f"{part!r} not in {errors[0]!r}"
    return errors[0]


# ---------------------------------------------------------------------------------------------- a fake model


def caption_responder(body: dict) -> str:
    """Deterministic, parseable answers for the loopback server: frame lines for Process 1, a sentence else.

    The text depends only on the request body, so any two runs of the same cells get the same answers."""
    texts = []
    for m in body.get("messages", []):
        content = m.get("content")
        if isinstance(content, str):
            texts.append(content)
        elif isinstance(content, list):
            texts += [p.get("text", "") for p in content if isinstance(p, dict)]
    prompt = "\n".join(texts)
    tag = request_digest(body)[:10]
    if "# Process 1" in prompt:
        return "\n".join(f"Frame {i}: the gripper moves toward the handle ({tag}-{i})" for i in range(1, 6))
    if "# Process 2" in prompt:
        return f"The robot reaches for the handle and pulls it ({tag})."
    return f"Open the door by pulling its handle ({tag})."


# ---------------------------------------------------------------------------------------------- run snapshots

# Fields that differ between a straight run and a resumed one by design: whether an answer came from the cache,
# how long the model took.
_RUN_VARIANT_REQUEST_FIELDS = ("from_cache", "latency_s")


def transcripts_of(run_dir: Path) -> dict[str, dict]:
    """Every transcript file of a run, parsed and validated, by relative path (request timings left out)."""
    from vlmproprio.transcripts import read_transcript

    out = {}
    root = run_dir / "transcripts"
    for path in sorted(root.rglob("*.json")) if root.is_dir() else []:
        t = read_transcript(path).to_dict()  # raises TranscriptError for a half-written or damaged file
        t["timing"] = None
        t["requests"] = [{k: v for k, v in r.items() if k not in _RUN_VARIANT_REQUEST_FIELDS} for r in t["requests"]]
        out[path.relative_to(run_dir).as_posix()] = t
    return out


def cache_answers(cache_dir: Path) -> dict[str, str]:
    """key -> answer text of every entry, after checking each entry's checksum and that no key is stored twice."""
    db = cache_dir / "cache.db"
    if not db.exists():
        return {}
    with sqlite3.connect(db) as conn:
        dup = conn.execute("SELECT key, COUNT(*) FROM Cache GROUP BY key HAVING COUNT(*) > 1").fetchall()
        assert dup == [], f"keys stored more than once: {dup}"
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    with ResponseCache(cache_dir) as cache:
        out = {}
        for key in cache:
            entry = cache.get(key)  # CacheCorruptError for a half-written or damaged entry
            assert entry is not None
            out[key] = entry.text
        return out


def run_file(run_dir: Path) -> dict | None:
    path = run_dir / "run.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else None


def temp_leftovers(root: Path) -> list[Path]:
    """Temporary files of atomic writes (``.<name>.<random>.tmp``) that a kill left behind."""
    return sorted(p for p in root.rglob(".*.tmp") if p.is_file())


def tree_snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime in ns) of every file under ``root``, and every folder (by its presence only; a folder's
    mtime changes whenever something is created in it): what a command may not touch."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_dir() and not p.is_symlink():
            out[rel + "/"] = (0, 0)
        else:
            st = p.lstat()
            out[rel] = (st.st_size, st.st_mtime_ns)
    return out


def changed_paths(before: dict, after: dict) -> set[str]:
    return {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)}


def all_files(*roots: Path) -> list[Path]:
    return sorted(p for root in roots if root.exists() for p in root.rglob("*") if p.is_file())


# ---------------------------------------------------------------------------------------------- raw cache rows


def cache_rows(cache_dir: Path) -> dict[str, tuple[int, bytes]]:
    """key -> (rowid, stored value bytes) straight from diskcache's SQLite table (keys are zlib'd JSON)."""
    import zlib

    with sqlite3.connect(cache_dir / "cache.db") as conn:
        rows = conn.execute("SELECT rowid, key, value FROM Cache").fetchall()
    return {json.loads(zlib.decompress(k)): (rowid, bytes(v)) for rowid, k, v in rows}


def set_cache_row(cache_dir: Path, rowid: int, value: bytes, mode: int | None = None) -> None:
    """Overwrite one stored value behind diskcache's back, as a disk fault or a person could."""
    with sqlite3.connect(cache_dir / "cache.db") as conn:
        if mode is None:
            conn.execute("UPDATE Cache SET value = ? WHERE rowid = ?", (value, rowid))
        else:
            conn.execute("UPDATE Cache SET value = ?, mode = ? WHERE rowid = ?", (value, mode, rowid))


def cache_env_sharing_embeddings(root: Path, tmp_path_factory) -> dict[str, str]:
    """A CLI environment whose cache root is ``root/cache`` (its own response cache) but whose embedding cache
    is shared by the session: sentence embeddings are deterministic, and computing them loads the encoder
    (~10 s) in every module that scores otherwise."""
    shared = tmp_path_factory.getbasetemp() / "shared-embeddings"
    shared.mkdir(exist_ok=True)
    (root / "cache").mkdir(parents=True, exist_ok=True)
    (root / "cache" / "embeddings").symlink_to(shared, target_is_directory=True)
    return cli_env(VLMPROPRIO_CACHE=str(root / "cache"))
