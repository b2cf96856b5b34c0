"""The README's "Add your model to the CI gates", end to end, for a `py:` model on four episodes.

In a copy of benchmark/ (so that the baselines and the claims entry it writes stay out of the checkout): record
a cassette, rebuild its embeddings sidecar, write the baselines with --force-regen (the first run reports each
new file as failed), read the observed verdicts and warnings from the skip reasons, write them into
claims.yml, and every gate passes.
"""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vlmproprio.episodes.manifest import write_manifest

REPO = Path(__file__).resolve().parents[1]
EPISODES = ("door_00", "door_01", "bin0_00", "bin1_00")  # two per task: both_shuffled lends within a task
CONDITIONS = "none,both,both_shuffled"  # what the four primary hypotheses compare
MODEL = "py:gatevlm:factory"

# a deterministic toy VLM whose captions depend on the frames it sees
TOY = """
import hashlib

WORDS = ("moves forward", "closes the gripper", "turns the handle down", "lifts the box up", "moves left")


def answer(request):
    text = "".join(m.text for m in request.messages)
    if "Summaries of the task:" in text:
        return "Open the door." if "door" in text.lower() else "Pick up the box and place it."
    if "Described robot arm actions:" in text:
        return "The robot arm " + WORDS[len(request.images) % len(WORDS)] + "."
    pick = [int(hashlib.sha256(i.data).hexdigest()[:6], 16) % 5 for i in request.images]
    return "\\n".join(f"Frame {n + 1}: The arm {WORDS[p]}." for n, p in enumerate(pick)) or "Frame 1: It moves."


def factory():
    return answer
"""


def _run(argv: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=600, check=False)


def _observed(output: str) -> tuple[dict[str, str], list[str]]:
    """The verdicts and warnings that the claims gates' skip reasons say were observed."""
    verdicts = dict(re.findall(r"observed (\w+): [^\n]*?\(all\): (not supported|supported|inconclusive)", output))
    # the combined claims: "observed <claim>: <verdict>, p = ... (why)"
    verdicts |= dict(re.findall(r"observed (\w+): (not supported|supported|inconclusive)(?:, p = \S+)? \(", output))
    warnings = re.search(r"no warnings recorded in benchmark/claims.yml for \S+; observed (\[.*?\])", output)
    assert warnings, output[-3000:]
    return verdicts, ast.literal_eval(warnings.group(1))


@pytest.mark.slow
def test_a_new_model_becomes_a_gate_by_the_readmes_steps(tmp_path: Path) -> None:
    fixtures = tmp_path / "fixtures"
    for eid in EPISODES:
        shutil.copytree(REPO / "fixtures" / "episodes" / eid, fixtures / "episodes" / eid)
    write_manifest(fixtures)
    (tmp_path / "pkgs").mkdir()
    (tmp_path / "pkgs" / "gatevlm.py").write_text(TOY)
    clone = tmp_path / "clone"  # benchmark/ and the conftest that loads its plugin, without the baselines
    shutil.copytree(REPO / "benchmark", clone / "benchmark", ignore=shutil.ignore_patterns("baselines", "__pycache__"))
    shutil.copy(REPO / "conftest.py", clone / "conftest.py")
    (clone / "pytest.ini").write_text("[pytest]\n")  # the clone is pytest's rootdir
    env = {k: v for k, v in os.environ.items() if not k.startswith(("VLMPROPRIO_", "PYTEST_"))}
    env |= {
        "VLMPROPRIO_CACHE": os.environ["VLMPROPRIO_CACHE"],
        "PYTHONPATH": os.pathsep.join([str(tmp_path / "pkgs"), str(REPO / "src")]),
    }
    cli = [sys.executable, "-m", "vlmproprio.cli"]
    gates = [sys.executable, "-m", "pytest", "benchmark", "--model", MODEL, f"--fixtures-dir={fixtures}"]
    gates += ["--conditions", CONDITIONS, "-p", "no:cacheprovider", "-q", "-rs"]

    # 1. record a cassette (and its embeddings sidecar)
    rec = _run([*cli, "run", "--model", MODEL, "--fixtures", str(fixtures), "--conditions", CONDITIONS,
                "--mode", "record", "--out", str(tmp_path / "runs" / "gatevlm"), "--no-progress"], tmp_path, env)  # fmt: skip
    assert rec.returncode == 0, rec.stderr[-3000:]
    (cassette,) = (fixtures / "responses").glob("py_gatevlm_factory-*.jsonl")
    sidecar = cassette.with_suffix(".embeddings.npz")
    assert sidecar.is_file()
    # 2. (re)build the sidecar
    sidecar.unlink()
    # (from the run: the cassette holds three conditions, a replay of the whole benchmark would need all nine)
    embed = _run([*cli, "cassette", "embed", "--model", MODEL, "--fixtures", str(fixtures), "--run-dir",
                  str(tmp_path / "runs" / "gatevlm"), "--no-progress"], tmp_path, env)  # fmt: skip
    assert embed.returncode == 0 and sidecar.is_file(), embed.stderr[-3000:]
    # 3. the baselines: every file is new, so pytest-regressions reports each as failed, having written it
    regen = _run([*gates, "--force-regen"], clone, env)
    assert regen.returncode == 1 and "File not found in data directory, created" in regen.stdout, regen.stdout[-3000:]
    baselines = clone / "benchmark" / "baselines" / cassette.stem
    assert len(list(baselines.rglob("*.yml"))) == len(EPISODES) * 3
    # 4. the cells pass; the claims gates skip and say what they observed
    seen = _run(gates, clone, env)
    assert seen.returncode == 0, seen.stdout[-3000:]
    verdicts, warnings = _observed(seen.stdout)
    from vlmproprio.verdicts import load_claims

    claims = load_claims()
    assert len(verdicts) == len(claims.hypotheses) + len(claims.combined), seen.stdout[-3000:]
    claims = clone / "benchmark" / "claims.yml"
    entry = "".join(f"    {h}: {v}\n" for h, v in verdicts.items())
    text = claims.read_text().replace("\nwarnings:\n", f"\n  {MODEL}:\n{entry}\nwarnings:\n  {MODEL}: {warnings}\n", 1)
    claims.write_text(text)
    # 5. every gate passes, none skipped
    gated = _run(gates, clone, env)
    assert gated.returncode == 0 and "skipped" not in gated.stdout, gated.stdout[-3000:]
