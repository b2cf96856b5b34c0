"""The power command: what the suite's episode structure can detect."""

from __future__ import annotations

import argparse
from pathlib import Path

from vlmproprio.cli.arguments import add_list, command
from vlmproprio.options import split_list


def cmd_power(args: argparse.Namespace) -> int:
    from vlmproprio import power

    base = power.PowerSettings()
    settings = power.PowerSettings(
        alpha=base.alpha if args.alpha is None else args.alpha,
        family=base.family if args.family is None else args.family,
        n_sims=base.n_sims if args.sims is None else args.sims,
        seed=base.seed if args.seed is None else args.seed,
    )
    groups: dict[str, int] = {}
    for name in split_list(args.set) or [power.SHIPPED, "extended"]:
        groups |= power.set_groups(name)
    analysis = power.analyse(
        settings,
        groups=groups,
        words=power.PAPER_WORDS if args.words is None else tuple(args.words),
        sd_words=power.DEFAULT_SD_WORDS if args.sd_words is None else args.sd_words,
        sd_f1=power.DEFAULT_SD_F1 if args.sd_f1 is None else args.sd_f1,
        correctness=power.DEFAULT_CORRECTNESS if args.correctness is None else tuple(args.correctness),
    )
    print(power.summary_markdown(analysis))
    for path in power.write_power(analysis, args.out):
        print(f"wrote {path}")
    return 0


def add_power(sub) -> None:
    p = command(sub, "power", cmd_power)
    add_list(
        p,
        "--set",
        "episode sets to analyse side by side: shipped (10 Door + 12 bin) and the named sets of "
        "record/named_sets.json, a comma list or repeated (default: shipped, extended)",
        "SETS",
    )
    p.add_argument("--alpha", type=float, help="family-wise alpha (default 0.05)")
    p.add_argument(
        "--family", type=int, help="primary hypotheses corrected together with Holm (default 4, as in claims.yml)"
    )
    p.add_argument("--sims", type=int, help="simulated data sets per point (default 1000)")
    p.add_argument("--seed", type=int, help="simulation seed (default: the statistics' seed)")
    pair = dict(type=float, nargs=2)  # a value without and one with state
    p.add_argument(
        "--words",
        **pair,
        metavar=("NONE", "BOTH"),
        help="mean words without and with state (default: the paper's 25.2 35.45)",
    )
    p.add_argument("--sd-words", type=float, help="per-episode SD of the paired word difference (default 10)")
    p.add_argument("--sd-f1", type=float, help="per-episode SD of the paired boundary-F1 difference (default 0.15)")
    p.add_argument(
        "--correctness",
        **pair,
        metavar=("P", "Q"),
        help="P(right) with and without state for the episodes-needed line (default 0.6 0.3)",
    )
    p.add_argument("--out", type=Path, default=Path("runs") / "power", help="output folder (default runs/power)")
