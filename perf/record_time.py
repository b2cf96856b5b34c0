"""Wall time of `vlmproprio record` for all 22 episodes into a temporary folder (target: <= 10 min on 2 cores).

    python perf/record_time.py [--episodes door_00 bin0_00]

Runs the recorder in a fresh process, exactly as a user would (robosuite +
MuJoCo, headless rendering), then compares the manifest it wrote with the
shipped fixtures' one: a recording that is not bit-identical is reported
(the time of a recording that differs would not be the time of this one).
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

from _common import FIXTURES, ROOT, emit, machine, table, write_json


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", nargs="+", help="only these episodes (default: all 22)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    with tempfile.TemporaryDirectory(prefix="vlmproprio-record-") as tmp:
        out = Path(tmp) / "fixtures"
        cmd = [sys.executable, "-m", "vlmproprio.cli", "record", "--fixtures", str(out)]
        cmd += ["--contact-sheets", str(Path(tmp) / "sheets")]
        if args.episodes:
            cmd += ["--episodes", *args.episodes]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
        if done.returncode != 0:
            raise SystemExit(f"record failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
        made = json.loads((out / "manifest.json").read_text())["files"]
        shipped = json.loads((FIXTURES / "manifest.json").read_text())["files"]
        differ = sorted(k for k, v in made.items() if shipped.get(k) != v)
        episodes = len({k.split("/")[1] for k in made if k.startswith("episodes/")})
    row = {
        "episodes": episodes,
        "wall_s": wall,
        "per_episode_s": wall / max(1, episodes),
        "files": len(made),
        "files_differing_from_shipped": len(differ),
        "target_s": 600,
        "ok": wall <= 600,
    }
    emit({"what": "machine", **machine(), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl (the recorder's default)")})
    emit({"what": "record", "command": " ".join(cmd[1:]), **row, "differing": differ[:10]})
    print()
    print(table([row], ["episodes", "wall_s", "per_episode_s", "files", "files_differing_from_shipped", "ok"]))
    write_json(args.out, {"machine": machine(), "row": row, "differing": differ})
    return 0 if row["ok"] and not differ else 1


if __name__ == "__main__":
    raise SystemExit(main())
