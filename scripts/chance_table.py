"""Regenerate the precomputed chance table (src/vlmproprio/evaluation/chance_table.json).

    python scripts/chance_table.py [--fixtures FIXTURES ...] [--out PATH]

Random chance of every count of segmentation points for every fixture episode's ground truth, exactly as
``ChanceTable`` would compute it, so scoring with an empty chance cache draws nothing. The committed table holds
the shipped fixtures' and the extended set's ground truths (``--fixtures fixtures --fixtures DIR`` with DIR from
``vlmproprio record --set extended --out DIR``), so that both score cold at the same cost per episode. Run it after adding or
re-recording episodes, or after changing anything ``evaluation.chance.chance_settings`` names (the table is
ignored, entry by entry or as a whole, when it does not match; tests/evaluation/test_chance.py checks it does).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from vlmproprio.episodes import load_episodes
from vlmproprio.evaluation.chance import CHANCE_TABLE_FILE, build_chance_table
from vlmproprio.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fixtures", type=Path, action="append", help="fixture folders (default: the shipped one)")
    ap.add_argument("--out", type=Path, default=CHANCE_TABLE_FILE)
    args = ap.parse_args(argv)
    t = time.perf_counter()
    c = time.process_time()
    episodes = [ep for root in args.fixtures or [ROOT / "fixtures"] for ep in load_episodes(root)]
    doc = build_chance_table(ep.frame_phases for ep in episodes)
    atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")
    n = sum(len(by_k) for by_k in doc["truths"].values())
    print(
        f"{args.out}: {len(doc['truths'])} ground truths, {n} counts "
        f"in {time.perf_counter() - t:.1f} s ({time.process_time() - c:.1f} s CPU)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
