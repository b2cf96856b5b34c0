"""Cached replay on CPU: the whole benchmark for one model (22 episodes x 8 conditions, scoring, segmentation
sweep, paired statistics), cold and warm, each in a fresh process.

    python benchmarks/replay_speed.py [--model tiny-qwen2-vl] [--model reference] [--repeat 2]

cold: a fresh process and an empty embedding cache (the sentence encoder must load and embed every caption);
warm: a fresh process with the embeddings cached. Targets (issue 7): <= 20 s cold, <= 5 s warm on 2 cores.
Also reports which heavy libraries the process imported (replay and warm scoring must import none).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

DRIVER = r"""
import json, sys, time
t0 = time.perf_counter()
from pathlib import Path
from vlmproprio.conditions import parse_conditions
from vlmproprio.runner import RunPlan, run
from vlmproprio.evaluation import score_run
t_import = time.perf_counter() - t0
out = Path(sys.argv[2])
t = time.perf_counter()
run(RunPlan(models=(sys.argv[1],), conditions=tuple(parse_conditions("all")), fixtures=Path(sys.argv[3]),
            out=out, mode="replay", progress=False))
t_run = time.perf_counter() - t
t = time.perf_counter()
tables = score_run(out, fixtures=Path(sys.argv[3]))
t_score = time.perf_counter() - t
heavy = [m for m in ("torch", "transformers", "sentence_transformers") if m in sys.modules]
print(json.dumps({"import_s": t_import, "run_s": t_run, "score_s": t_score, "heavy": heavy,
                  "transcripts": len(tables.rows), "embeddings": tables.timing["embeddings"],
                  "score_timing": {k: v for k, v in tables.timing.items() if k.endswith("_s")}}))
"""


def measure(model: str, cache_root: Path, out: Path) -> dict:
    env = {**os.environ, "VLMPROPRIO_CACHE": str(cache_root), "PYTHONPATH": str(ROOT / "src")}
    t = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", DRIVER, model, str(out), str(ROOT / "fixtures")],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{model}: the replay run failed:\n{proc.stderr[-3000:]}")
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    res["wall_s"] = wall
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", help="default: tiny-qwen2-vl and reference")
    ap.add_argument("--repeat", type=int, default=2, help="warm runs per model (default 2)")
    args = ap.parse_args()
    print(f"{'model':<16}{'run':<6}{'wall s':>8}{'import':>8}{'replay':>8}{'score':>8}{'embedded':>10}  heavy imports")
    for model in args.model or ["tiny-qwen2-vl", "reference"]:
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp) / "cache"
            for i in range(1 + args.repeat):
                r = measure(model, cache, Path(tmp) / f"run{i}")
                e = r["embeddings"]
                print(
                    f"{model:<16}{'cold' if i == 0 else 'warm':<6}{r['wall_s']:>8.2f}{r['import_s']:>8.2f}"
                    f"{r['run_s']:>8.2f}{r['score_s']:>8.2f}{e['computed']:>10}  {', '.join(r['heavy']) or '-'}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
