"""The test process's cache root (tests/conftest.py) is removed when the process exits, however pytest ends."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_run_that_stops_on_a_usage_error_leaves_no_cache_root(tmp_path):
    env = {**os.environ, "TMPDIR": str(tmp_path)}
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
