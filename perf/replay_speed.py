"""Cached replay on CPU: the whole benchmark for one model (22 episodes x 8 conditions, scoring, segmentation
sweep, paired statistics), cold and warm, each in a fresh process.

    python perf/replay_speed.py [--model tiny-qwen2-vl] [--model reference] [--repeat 2]

cold: a fresh process and an empty embedding cache (caption embeddings come from the model's sidecar,
fixtures/responses/<model>.embeddings.npz; without one the sentence encoder would load and embed every caption);
warm: a fresh process with the embeddings cached. Targets: issue 7 <= 20 s cold, <= 5 s warm; issue 17 <= 5 s
cold, <= 2 s warm on 2 cores. Also reports which heavy libraries the process imported (none, with sidecars).

Replay (with answers that call no model) and scoring use the default number of workers (vlmproprio.parallel:
the usable cores, at most 4; 2 on the CI machine); set VLMPROPRIO_WORKERS=1 to time one process alone.

--split N (warm, after the runs above): the ceiling of N-core parallelism for this work. N fresh processes
start together, each replaying and scoring every N-th episode into its own run folder; the wall time is from
the first start to the last exit. No merge, no shared statistics: a parallel version of the whole run could
only be slower than this.

--against DIR: the same runs of another checkout of vlmproprio (its src/ and fixtures/, e.g. a git worktree of
an older commit), alternated with this checkout's, each with its own embedding cache: the machine's speed moves
from hour to hour, so code is compared side by side, by the ratio of warm wall times.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from _common import FIXTURES, ROOT, emit, machine, table, write_json

DRIVER = r"""
import json, sys, time
t0 = time.perf_counter()
from pathlib import Path
from vlmproprio.conditions import parse_conditions
from vlmproprio.runner import RunPlan, run
from vlmproprio.evaluation import score_run
t_import = time.perf_counter() - t0
out = Path(sys.argv[2])
episodes = tuple(sys.argv[4].split(",")) if len(sys.argv) > 4 else None
t = time.perf_counter()
run(RunPlan(models=(sys.argv[1],), conditions=tuple(parse_conditions("all")), fixtures=Path(sys.argv[3]),
            out=out, mode="replay", progress=False, episode_ids=episodes))
t_run = time.perf_counter() - t
t = time.perf_counter()
tables = score_run(out, fixtures=Path(sys.argv[3]))
t_score = time.perf_counter() - t
heavy = [m for m in ("torch", "transformers", "sentence_transformers") if m in sys.modules]
print(json.dumps({"import_s": t_import, "run_s": t_run, "score_s": t_score, "heavy": heavy,
                  "transcripts": len(tables.rows), "embeddings": tables.timing["embeddings"],
                  "score_timing": {k: v for k, v in tables.timing.items() if k.endswith("_s")}}))
"""


def _start(
    model: str,
    cache_root: Path,
    out: Path,
    files: contextlib.ExitStack,
    episodes: Sequence[str] = (),
    code: Path = ROOT,
    fixtures: Path | None = None,
):
    """The driver of checkout ``code`` started on ``episodes`` (default: all) of ``fixtures`` (default: the
    checkout's own); its stdout and stderr go to temporary files in ``files``."""
    env = {**os.environ, "VLMPROPRIO_CACHE": str(cache_root), "PYTHONPATH": str(code / "src")}
    # closed by the caller's ExitStack, after _finish has read them
    stdout = files.enter_context(tempfile.TemporaryFile())  # noqa: SIM115
    stderr = files.enter_context(tempfile.TemporaryFile())  # noqa: SIM115
    fixtures = fixtures or code / FIXTURES.relative_to(ROOT)
    argv = [sys.executable, "-c", DRIVER, model, str(out), str(fixtures), *([",".join(episodes)] if episodes else [])]
    return subprocess.Popen(argv, stdout=stdout, stderr=stderr, env=env), stdout, stderr


def _finish(model: str, proc: subprocess.Popen, stdout, stderr) -> dict:
    # the kernel's accounting of the child: CPU seconds do not grow with other processes' load as wall time does
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    stdout.seek(0)
    stderr.seek(0)
    if proc.returncode != 0:
        raise SystemExit(f"{model}: the replay run failed:\n{stderr.read().decode()[-3000:]}")
    res = json.loads(stdout.read().decode().strip().splitlines()[-1])
    return res | {"cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024}


def measure(model: str, cache_root: Path, out: Path, code: Path = ROOT, fixtures: Path | None = None) -> dict:
    t = time.perf_counter()
    with contextlib.ExitStack() as files:
        res = _finish(model, *_start(model, cache_root, out, files, code=code, fixtures=fixtures))
    return res | {"wall_s": time.perf_counter() - t}


def measure_split(model: str, cache_root: Path, tmp: Path, n: int) -> dict:
    """N processes at once, each on every N-th episode (see the module docstring): the parallel ceiling."""
    from vlmproprio.episodes import list_episode_ids

    ids = list_episode_ids(FIXTURES)  # the order load_episodes uses; each process verifies what it loads
    t = time.perf_counter()
    with contextlib.ExitStack() as files:
        started = [_start(model, cache_root, tmp / f"split{n}_{i}", files, ids[i::n]) for i in range(n)]
        parts = [_finish(model, *s) for s in started]
    return {
        "wall_s": time.perf_counter() - t,
        "cpu_s": sum(p["cpu_s"] for p in parts),
        "peak_rss_mb": max(p["peak_rss_mb"] for p in parts),
        "import_s": max(p["import_s"] for p in parts),
        "run_s": max(p["run_s"] for p in parts),
        "score_s": max(p["score_s"] for p in parts),
        "embeddings": {
            "computed": sum(p["embeddings"]["computed"] for p in parts),
            "sidecar": sum(p["embeddings"].get("sidecar", 0) for p in parts),
        },
        "heavy": sorted({h for p in parts for h in p["heavy"]}),
        "score_timing": [p["score_timing"] for p in parts],
    }


def _row(model: str, code: str, run: str, r: dict) -> dict:
    return {
        "model": model,
        "code": code,
        "run": run,
        "wall_s": r["wall_s"],
        "cpu_s": r["cpu_s"],
        "peak_rss_mb": r["peak_rss_mb"],
        "import_s": r["import_s"],
        "replay_s": r["run_s"],
        "score_s": r["score_s"],
        "embedded": r["embeddings"]["computed"],
        "from_sidecar": r["embeddings"].get("sidecar", 0),
        "heavy_imports": ", ".join(r["heavy"]) or "-",
    }


def _ratio(rows: Sequence[dict]) -> dict:
    """This checkout's warm wall and CPU time over the other's, per round (a round: the two run back to back)."""
    this = [r for r in rows if r["run"] == "warm" and r["code"] == "this"]
    other = [r for r in rows if r["run"] == "warm" and r["code"] == "against"]
    out = {}
    for what in ("wall_s", "cpu_s"):
        ratios = sorted(a[what] / b[what] for a, b in zip(this, other, strict=True))
        out[what.replace("_s", "_ratios")] = ratios
        out[what.replace("_s", "_ratio_median")] = statistics.median(ratios)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", help="default: tiny-qwen2-vl and reference")
    ap.add_argument("--repeat", type=int, default=2, help="warm runs per model (default 2)")
    ap.add_argument("--split", type=int, default=0, metavar="N", help="also the N-process ceiling (module docstring)")
    ap.add_argument("--against", type=Path, metavar="DIR", help="also another checkout, side by side (docstring)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    emit({"what": "machine", **machine()})
    checkouts = {"this": ROOT} | ({"against": args.against.resolve()} if args.against else {})
    rows, ratios = [], {}
    for model in args.model or ["tiny-qwen2-vl", "reference"]:
        with tempfile.TemporaryDirectory() as tmp:
            caches = {name: Path(tmp) / f"cache-{name}" for name in checkouts}
            for i in range(1 + args.repeat):  # a cold round, then warm rounds; the other checkout first in those
                for name in reversed(checkouts) if i else checkouts:
                    r = measure(model, caches[name], Path(tmp) / f"{name}-run{i}", checkouts[name])
                    rows.append(_row(model, name, "cold" if i == 0 else "warm", r))
                    emit({"what": "replay", **rows[-1], "score_timing": r["score_timing"]})
            if args.split > 1:
                r = measure_split(model, caches["this"], Path(tmp), args.split)
                rows.append(_row(model, "this", f"warm, {args.split} at once", r))
                emit({"what": "replay", **rows[-1], "score_timing": r["score_timing"]})
        if args.against:
            ratios[model] = _ratio([r for r in rows if r["model"] == model])
            emit({"what": "ratio", "model": model, **ratios[model]})
    print()
    cols = [
        "model",
        *(["code"] if args.against else []),
        "run",
        "wall_s",
        "cpu_s",
        "peak_rss_mb",
        "import_s",
        "replay_s",
        "score_s",
        "embedded",
        "from_sidecar",
        "heavy_imports",
    ]
    print(table(rows, cols))
    for model, r in ratios.items():
        print(
            f"\n{model}: this checkout's warm wall time / {args.against}'s, median of {len(r['wall_ratios'])} "
            f"rounds: {r['wall_ratio_median']:.3f} (CPU time: {r['cpu_ratio_median']:.3f})"
        )
    write_json(args.out, {"machine": machine(), "rows": rows, "ratios": ratios})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
