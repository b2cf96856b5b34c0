"""The wheel works on its own: built from the repository, installed into a fresh virtual environment without the
source tree on the path, and used from an empty folder (a run with its report, and the benchmark).

The fresh environment sees this environment's third-party packages (torch, transformers, ...) through a ``.pth``
line naming their site-packages folder: a plain path line does not run the ``.pth`` files inside that folder, so
an editable install of vlmproprio there stays invisible, and the test checks that vlmproprio comes from the wheel.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from vlmproprio.conditions import CONDITIONS

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "fixtures"

pytestmark = pytest.mark.slow


def _clean_env(tmp: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VLMPROPRIO_", "PYTEST_"))}
    env |= {
        "HOME": str(tmp / "home"),
        "VLMPROPRIO_CACHE": str(tmp / "cache"),
        "HF_HUB_OFFLINE": "1",
        "OMP_NUM_THREADS": "1",
    }
    return env


def _run(cmd: list, cwd: Path, env: dict, timeout: int = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )
    assert proc.returncode == 0, f"{cmd}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _setuptools_major() -> int:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return int(version("setuptools").split(".")[0])
    except (PackageNotFoundError, ValueError):
        return 0


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the sources (a build in place would write build/ into the checkout)."""
    src = tmp_path_factory.mktemp("wheel-src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "src", src / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    out = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", out, src]
    if _setuptools_major() >= 77:  # the build backend pyproject.toml asks for is here: build offline with it
        cmd.insert(5, "--no-build-isolation")
    _run(cmd, src, {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    (whl,) = out.glob("vlmproprio-*.whl")
    return whl


def test_the_wheel_holds_every_data_file_of_the_package(wheel: Path) -> None:
    package = REPO / "src" / "vlmproprio"
    data = {
        p.relative_to(package.parent).as_posix()
        for p in package.rglob("*")
        if p.is_file() and p.suffix != ".py" and "__pycache__" not in p.parts
    }
    names = set(zipfile.ZipFile(wheel).namelist())
    assert data, "no data files found in the package"
    assert not data - names, f"missing from the wheel: {sorted(data - names)}"
    assert "vlmproprio/prompts/paper/process1.txt" in names
    entry_points = next((n for n in names if n.endswith(".dist-info/entry_points.txt")), None)
    text = zipfile.ZipFile(wheel).read(entry_points).decode() if entry_points else ""
    assert "pytest11" not in text  # no plugin forced on every pytest session of the environment


@pytest.fixture(scope="module")
def venv(wheel: Path, tmp_path_factory) -> Path:
    """A fresh venv with the wheel installed and this environment's third-party packages visible.

    The venv gets no pip of its own (ensurepip byte-compiles all of pip: seconds of CPU for nothing the tests
    use): this environment's pip installs the wheel into it (``pip --python``), as a real install; and without
    ``.pyc`` files up front (``--no-compile``): the venv's Python writes them for the modules the tests import."""
    root = tmp_path_factory.mktemp("wheel-venv")
    venv = root / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], root, _clean_env(root))
    (site,) = (venv / "lib").glob("python*/site-packages")
    (site / "zz_shared_site_packages.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    pip = [sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install", "-q", "--no-deps"]
    _run([*pip, "--no-index", "--no-compile", wheel], root, {**_clean_env(root), "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    return venv


def test_the_installed_wheel_runs_and_reports_from_an_empty_folder(venv: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    env = _clean_env(tmp_path)
    py = venv / "bin" / "python"
    where = _run([py, "-c", "import vlmproprio; print(vlmproprio.__file__)"], empty, env).stdout.strip()
    assert Path(where).is_relative_to(venv), f"vlmproprio imported from {where}, not from the wheel"
    cli = venv / "bin" / "vlmproprio"
    assert _run([cli, "--version"], empty, env).stdout.strip() == "vlmproprio 0.1.0"
    _run([cli, "verify", "--fixtures", FIXTURES], empty, env)
    out = _run([cli, "run", "--model", "reference", "--fixtures", FIXTURES, "--report", "--no-progress"], empty, env)
    run_dir = empty / "runs" / "latest"
    assert (run_dir / "report" / "index.html").is_file(), out.stdout
    assert (run_dir / "scores" / "frames.csv").is_file()
    manifest = json.loads((run_dir / "run.json").read_text())
    assert len(manifest["episodes"]) == 22 and len(manifest["conditions"]) == len(CONDITIONS)
    assert sorted(p.name for p in empty.iterdir()) == ["runs"]  # nothing else written into the working folder


def test_the_benchmark_runs_against_the_installed_wheel(venv: Path, tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    env = _clean_env(tmp_path)
    cmd = [venv / "bin" / "python", "-m", "pytest", REPO / "benchmark", "--model", "reference"]
    cmd += ["--fixtures-dir", FIXTURES, "--episodes", "door_00,bin0_00", "--conditions", "none,both"]
    proc = _run([*cmd, "-q", "-p", "no:cacheprovider"], empty, env)
    # 2 episodes x 2 conditions x 3 gates, and the claims file's own check; the verdict gates (4 hypotheses, 2
    # combined claims and the warnings) skip: out-of-sample numbers need every episode
    assert "13 passed, 7 skipped" in proc.stdout, proc.stdout[-2000:]
    # the conftest's plugin came from the wheel, not from the source tree
    probe = [venv / "bin" / "python", "-c", "import vlmproprio.pytest_plugin as p; print(p.__file__)"]
    assert Path(_run(probe, empty, env).stdout.strip()).is_relative_to(venv)
