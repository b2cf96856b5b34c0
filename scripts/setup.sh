#!/usr/bin/env bash
# Create ./.venv and install vlmproprio with every extra, CPU-only.
# torch is installed first and pinned: on this machine kind torch==2.13.0 is a local CPU wheel, while an
# unpinned torch (asked for by transformers or sentence-transformers) would pull a multi-GB CUDA build.
# Idempotent and quick on a second run: nothing is reinstalled while pyproject.toml is unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
STAMP=.venv/.vlmproprio-installed

# Debian's headless Chromium: a test renders the HTML report in it (that test skips, saying so, without it).
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  { apt-get install -y -qq chromium || { apt-get update -qq && apt-get install -y -qq chromium; }; } >/dev/null 2>&1 \
    || echo "setup: could not install chromium; the report's browser test will be skipped" >&2
fi

# The package's bytecode, written now: an editable install leaves src/ uncompiled, and where
# PYTHONDONTWRITEBYTECODE is set (as on this project's machines) every process, each CLI subprocess the tests
# start included, would compile all of it again (~0.2 s of CPU each). Python still checks each .pyc against its
# source, so an edited module is never run stale; compileall skips what is already up to date.
# The same for the test suite: pytest caches its assertion-rewritten test modules as bytecode too, and without
# that cache every xdist worker and every pytest session the tests start rewrites them all again (about a sixth of
# the README's test command on 2 cores). Collecting the suite
# once with bytecode writing allowed fills both caches (~15 s); a failure here is left for the tests to report.
compile_src() {
  .venv/bin/python -m compileall -q -j 0 src >/dev/null
  env -u PYTHONDONTWRITEBYTECODE .venv/bin/python -m pytest --collect-only -q -n 0 -p no:cacheprovider \
    >/dev/null 2>&1 || true
}

want=$( (cat pyproject.toml; echo "$TORCH_SPEC") | sha256sum | cut -d' ' -f1)
if [ -x .venv/bin/python ] && [ "$(cat "$STAMP" 2>/dev/null)" = "$want" ]; then
  compile_src
  exit 0
fi
# A .venv that is a file is a PEP 832 redirect to another tool's environment (tox writes one unless told not to):
# this script's environment lives at .venv, so the redirect gives way to it.
if [ -f .venv ] && [ ! -L .venv ]; then
  echo "setup: replacing the .venv redirect file (to $(head -c 200 .venv)) with the project's environment" >&2
  rm -f .venv
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
pip_install() { .venv/bin/python -m pip install --quiet --disable-pip-version-check "$@" 2>&1 | grep -v -e "^WARNING: Location" -e "BuildBackendWarning" -e "return '\\\\n'.join" || true; }
pip_install "$TORCH_SPEC"
pip_install -e ".[all,dev]"
check="import torch, transformers, sentence_transformers, robosuite, fastapi, uvicorn, jsonschema, platformdirs, vlmproprio"
.venv/bin/python -c "$check" >/dev/null 2>&1 \
  || { .venv/bin/python -c "$check"; echo "setup: the install is incomplete (see above)" >&2; exit 1; }
if .venv/bin/python -c "import torchvision" 2>/dev/null; then
  echo "setup: torchvision is installed in .venv; it breaks Qwen2-VL beside the CPU torch: remove it" >&2
  exit 1
fi
compile_src
echo "$want" > "$STAMP"
echo "setup: .venv ready ($(.venv/bin/python -c 'import torch, transformers; print("torch", torch.__version__, "transformers", transformers.__version__)'))"
