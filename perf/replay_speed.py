"""Cached replay on CPU: the whole benchmark for one model (22 episodes x 8 conditions, scoring, segmentation
sweep, paired statistics), cold and warm, each in a fresh process.

    python perf/replay_speed.py [--model tiny-qwen2-vl] [--model reference] [--repeat 2]

cold: a fresh process and an empty embedding cache (caption embeddings come from the model's sidecar,
fixtures/responses/<model>.embeddings.npz; without one the sentence encoder would load and embed every caption);
warm: a fresh process with the embeddings cached. Targets: issue 7 <= 20 s cold, <= 5 s warm; issue 17 <= 5 s
cold, <= 2 s warm on 2 cores. Also reports which heavy libraries the process imported (none, with sidecars).
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
    with tempfile.TemporaryFile() as stdout, tempfile.TemporaryFile() as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-c", DRIVER, model, str(out), str(FIXTURES)], stdout=stdout, stderr=stderr, env=env
        )
        # the kernel's accounting of the child: CPU seconds do not grow with other processes' load as wall time does
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t
        stdout.seek(0)
        stderr.seek(0)
        text, err = stdout.read().decode(), stderr.read().decode()
    if proc.returncode != 0:
        raise SystemExit(f"{model}: the replay run failed:\n{err[-3000:]}")
    res = json.loads(text.strip().splitlines()[-1])
    res |= {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", action="append", help="default: tiny-qwen2-vl and reference")
    ap.add_argument("--repeat", type=int, default=2, help="warm runs per model (default 2)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    emit({"what": "machine", **machine()})
    rows = []
    for model in args.model or ["tiny-qwen2-vl", "reference"]:
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp) / "cache"
            for i in range(1 + args.repeat):
                r = measure(model, cache, Path(tmp) / f"run{i}")
                row = {
                    "model": model,
                    "run": "cold" if i == 0 else "warm",
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
                rows.append(row)
                emit({"what": "replay", **row, "score_timing": r["score_timing"]})
    print()
    cols = [
        "model",
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
    write_json(args.out, {"machine": machine(), "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
