"""Scoring that scales: replay + scoring of the extended set against the shipped set, per episode, in one run.

    python perf/score_scale.py --extended DIR [--model reference] [--repeat 2] [--out FILE]

DIR is the extended set as ``vlmproprio record --set extended --out DIR`` left it (216 episodes). The script
records the model's answers for it once, untimed, into a copy of DIR made of hard links (so DIR and its
manifest stay as they are): ``run --mode record`` writes the cassette and its embedding sidecar there, as the
shipped fixtures hold them. Then, alternating the two sets in each round so that the machine's drift hits
both: the whole benchmark for the model in a fresh process (every episode x 9 conditions replayed, scoring,
the segmentation sweep, chance baselines, paired statistics), *cold* (an empty cache root: embeddings from
the sidecar, chance computed) and *warm* (the same cache root again). Reported per set: wall and CPU time,
both per episode, and the peak RSS of the process (``os.wait4``). Target (issue 34): the extended set's time
per episode at most 1.2x the shipped set's, peak memory bounded.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import FIXTURES, ROOT, emit, machine, table, write_json
from replay_speed import measure

TARGET_RATIO = 1.2


def _linked_copy(src: Path, dst: Path) -> Path:
    """``src`` as hard links (episodes are never written to; a recorded cassette is a new file)."""
    shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns(".partial"))
    return dst


def _record_answers(model: str, fixtures: Path, cache_root: Path) -> float:
    t = time.perf_counter()
    argv = [sys.executable, "-m", "vlmproprio.cli", "run", "--model", model, "--fixtures", str(fixtures)]
    argv += ["--mode", "record", "--out", str(fixtures.parent / "record-run"), "--no-progress"]
    env = {**os.environ, "VLMPROPRIO_CACHE": str(cache_root), "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.run(argv, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"recording {model}'s answers for {fixtures} failed:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t


def _episodes(fixtures: Path) -> int:
    return sum(1 for p in (fixtures / "episodes").iterdir() if (p / "episode.json").is_file())


def _ratios(rows: list[dict], run: str, what: str) -> list[float]:
    ext = [r for r in rows if r["set"] == "extended" and r["run"] == run]
    shipped = [r for r in rows if r["set"] == "shipped" and r["run"] == run]
    return [a[what] / b[what] for a, b in zip(ext, shipped, strict=True)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--extended", type=Path, required=True, help="the folder `record --set extended` wrote")
    ap.add_argument("--model", default="reference", help="a rule-based model (default: reference)")
    ap.add_argument("--repeat", type=int, default=2, help="rounds (each: both sets, cold then warm; default 2)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    emit({"what": "machine", **machine()})
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ext = _linked_copy(args.extended.resolve(), tmp / "extended" / "fixtures")
        emit({"what": "prepare", "record_s": _record_answers(args.model, ext, tmp / "cache-record")})
        sets = {"shipped": FIXTURES, "extended": ext}
        n_eps = {name: _episodes(path) for name, path in sets.items()}
        for i in range(args.repeat):
            order = list(sets) if i % 2 == 0 else list(reversed(sets))
            for name in order:
                cache = tmp / f"cache-{name}-{i}"
                for run in ("cold", "warm"):
                    r = measure(args.model, cache, tmp / f"{name}-{i}-{run}", fixtures=sets[name])
                    n = n_eps[name]
                    row = {
                        "set": name,
                        "round": i,
                        "run": run,
                        "episodes": n,
                        "transcripts": r["transcripts"],
                        "wall_s": r["wall_s"],
                        "wall_per_episode_s": r["wall_s"] / n,
                        "cpu_per_episode_s": r["cpu_s"] / n,
                        "replay_s": r["run_s"],
                        "score_s": r["score_s"],
                        "peak_rss_mb": r["peak_rss_mb"],
                        "embedded": r["embeddings"]["computed"],
                        "heavy_imports": ", ".join(r["heavy"]) or "-",
                    }
                    rows.append(row)
                    emit({"what": "score", **row, "score_timing": r["score_timing"]})
    summary = {}
    for run in ("cold", "warm"):
        for what in ("wall_per_episode_s", "cpu_per_episode_s"):
            ratios = _ratios(rows, run, what)
            summary[f"{run} {what}"] = {"ratios": ratios, "median": statistics.median(ratios)}
    peak = {name: max(r["peak_rss_mb"] for r in rows if r["set"] == name) for name in ("shipped", "extended")}
    emit({"what": "summary", "ratios": summary, "peak_rss_mb": peak})
    print()
    cols = ["set", "round", "run", "episodes", "transcripts", "wall_s", "wall_per_episode_s", "cpu_per_episode_s"]
    print(table(rows, [*cols, "replay_s", "score_s", "peak_rss_mb", "embedded", "heavy_imports"]))
    print()
    for key, v in summary.items():
        verdict = "meets" if v["median"] <= TARGET_RATIO else "misses"
        print(
            f"{key}: extended / shipped, median of {len(v['ratios'])} rounds: {v['median']:.2f} "
            f"({verdict} the target <= {TARGET_RATIO})"
        )
    print(f"peak RSS: shipped {peak['shipped']:.0f} MB, extended {peak['extended']:.0f} MB")
    write_json(args.out, {"machine": machine(), "rows": rows, "summary": summary, "peak_rss_mb": peak})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
