"""The test session's cache root (tests/conftest.py): one per session, shared by its xdist workers, removed at exit."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_this_process_uses_the_session_cache_root_of_its_owner():
    owner, _, root = os.environ["VLMPROPRIO_TEST_CACHE_OWNER"].partition(":")
    # an xdist worker shares its controller's root; a run in one process owns its own
    expected_owner = os.getppid() if os.environ.get("PYTEST_XDIST_WORKER") else os.getpid()
    assert int(owner) == expected_owner
    assert os.environ["VLMPROPRIO_CACHE"] == root and Path(root).is_dir()


def test_a_run_that_stops_on_a_usage_error_leaves_no_cache_root(tmp_path):
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    env.pop("VLMPROPRIO_TEST_CACHE_OWNER", None)  # as a developer's shell has it
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "0", "-p", "no:cacheprovider", "--mode", "bogus", "tests/test_stats.py"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 4, proc.stderr  # pytest's usage error
    assert "bogus" in proc.stderr
    assert not list(tmp_path.glob("vlmproprio-test-cache-*"))
