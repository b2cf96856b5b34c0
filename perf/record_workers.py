"""Wall time of recording a new episode set with 1 and with 2 worker processes, and their ratio (target >= 1.6x
on 2 cores).

    python perf/record_workers.py [--task stack] [--count 8] [--seed 0] [--max-steps N] [--two-first]

Runs `vlmproprio record --task T --count N --seed S --out DIR --workers W` in a fresh process for W = 1 then
W = 2, each into its own temporary folder, exactly as a user would, and checks that the two sets are
bit-identical (their manifests list the same digests). The load average before each run is printed with it:
on a machine other work shares, the ratio says as much about that work as about the recorder.
Needs the [record] extra (robosuite 1.5.2, mujoco 3.3.7).
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

from _common import ROOT, emit, machine, table, write_json


def _record(task: str, count: int, seed: int, workers: int, max_steps: int | None, out: Path) -> dict:
    cmd = [sys.executable, "-m", "vlmproprio.cli", "record", "--task", task, "--count", str(count)]
    cmd += ["--seed", str(seed), "--out", str(out), "--workers", str(workers), "--no-progress"]
    if max_steps is not None:
        cmd += ["--max-steps", str(max_steps)]
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"record failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    files = json.loads((out / "manifest.json").read_text())["files"]
    return {"workers": workers, "episodes": count, "wall_s": wall, "load_before": load, "files": files}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--task", default="stack", help="catalog task (default: stack)")
    ap.add_argument("--count", type=int, default=8, help="episodes per set (default: 8)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-steps", type=int, help="cut episodes after this many steps (default: whole episodes)")
    ap.add_argument("--two-first", action="store_true", help="run 2 workers before 1 (load drifts on a shared machine)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="vlmproprio-record-workers-") as tmp:
        for workers in (2, 1) if args.two_first else (1, 2):
            out = Path(tmp) / f"w{workers}"
            rows.append(_record(args.task, args.count, args.seed, workers, args.max_steps, out))
    rows.sort(key=lambda r: r["workers"])
    same = rows[0].pop("files") == rows[1].pop("files")
    ratio = rows[0]["wall_s"] / rows[1]["wall_s"]
    for r in rows:
        r["per_episode_s"] = r["wall_s"] / r["episodes"]
    emit({"what": "machine", **machine(), "usable_cores": len(os.sched_getaffinity(0))})
    for r in rows:
        emit({"what": "record", "task": args.task, **r})
    summary = {"what": "ratio", "speedup_2_over_1": ratio, "target": 1.6, "ok": ratio >= 1.6, "bit_identical": same}
    emit(summary)
    print()
    print(table(rows, ["workers", "episodes", "wall_s", "per_episode_s", "load_before"]))
    print(f"\n2 workers vs 1: {ratio:.2f}x (target >= 1.6); sets bit-identical: {same}")
    write_json(args.out, {"machine": machine(), "rows": rows, "summary": summary})
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
