"""The environment around the package: scripts/setup.sh beside other tools' files, and a gitignore that covers
what the documented commands write into the clone."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCUMENTED = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
# a path a documented command writes: --out DIR, --run-dir DIR, `python -m venv DIR`, `export-dataset DIR`
WRITES = re.compile(r"(?:--out|--run-dir|-m venv|export-dataset)\s+([A-Za-z0-9_.][\w./-]*)")

STUB_PYTHON = """#!/bin/sh
# a stand-in interpreter: `-m venv DIR` makes DIR/bin/python (this script); torchvision is not importable
case "$*" in
  *"-m venv"*) mkdir -p "$3/bin" && cp "$0" "$3/bin/python" ;;
  *torchvision*) exit 1 ;;
esac
exit 0
"""


def _documented_outputs() -> set[str]:
    found = set()
    for doc in DOCUMENTED:
        for match in WRITES.finditer(doc.read_text(encoding="utf-8")):
            path = match.group(1).rstrip(".")
            if not path.startswith(("/", "~", "path/", "OUT", "DIR")) and path.upper() != path:
                found.add(f"{path}/x")  # a file the command writes inside that folder
    return found


def test_the_gitignore_covers_what_documented_commands_write() -> None:
    outputs = _documented_outputs() | {"logs/x.eval", ".vlmproprio-cache/x"}  # inspect's log folder, the cache
    assert len(outputs) >= 5, outputs  # the pattern still finds the README's commands
    proc = subprocess.run(
        ["git", "check-ignore", "--no-index", "-v", "-n", *sorted(outputs)],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
    )
    unignored = [line.split("\t")[-1] for line in proc.stdout.splitlines() if line.startswith("::")]
    assert not unignored, f"documented commands write these into the clone, and git would see them: {unignored}"


@pytest.mark.skipif(shutil.which("sh") is None, reason="needs a POSIX shell")
def test_setup_replaces_a_venv_redirect_file(tmp_path: Path) -> None:
    (tmp_path / "scripts").mkdir()
    shutil.copy(REPO / "scripts" / "setup.sh", tmp_path / "scripts" / "setup.sh")
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    (tmp_path / ".venv").write_text(".tox/tests\n")  # what tox writes (PEP 832) where no .venv folder is
    stub = tmp_path / "python-stub"
    stub.write_text(STUB_PYTHON)
    stub.chmod(0o755)
    env = {**os.environ, "PYTHON": str(stub), "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin"}
    proc = subprocess.run(
        ["bash", str(tmp_path / "scripts" / "setup.sh")], env=env, capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / ".venv" / "bin" / "python").is_file()
    assert "redirect file" in proc.stderr
