"""How much each condition's numbers still tell about the episode: their correlation with the true states."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from vlmproprio.conditions import CONTROLS, PAPER_CONDITIONS, STATE_DIMENSIONS, get_condition, state_correlations
from vlmproprio.episodes import Episode, list_episode_ids, load_episodes


def control_correlations(root: Path, episodes: dict[str, Episode], conditions: Sequence[str]) -> dict:
    """Per condition with numeric state (controls and the paper's own-state conditions alike), per task and
    state dimension: the mean, min and max over episodes of the Pearson r between the numbers the prompts
    showed and the episode's true states (conditions.state_correlations) -- how much a control still tells."""
    known = [c for c in conditions if c in (*PAPER_CONDITIONS, *CONTROLS)]
    numeric = [get_condition(c) for c in known if get_condition(c).numeric_state]
    if not numeric:
        return {}
    peers = list(episodes.values())
    if any(c.source in ("shuffled", "permuted") for c in numeric):
        # partners come from every episode of the fixtures, as in the run (runner.run); those the run already
        # loaded are not read again (the whole benchmark's run has them all)
        missing = [e for e in list_episode_ids(root) if e not in episodes]
        if missing:
            peers += load_episodes(root, missing, verify=False)
    out: dict = {}
    for cond in numeric:
        per_task: dict[str, dict[str, list[float]]] = {}
        for ep in sorted(episodes.values(), key=lambda e: e.episode_id):
            rs = state_correlations(ep, cond, peers)
            for task in (ep.task, "all"):
                for dim, r in rs.items():
                    if r is not None:
                        per_task.setdefault(task, {}).setdefault(dim, []).append(r)
        out[cond.name] = {
            task: {
                dim: {"mean_r": math.fsum(v) / len(v), "min_r": min(v), "max_r": max(v), "n": len(v)}
                for dim in STATE_DIMENSIONS
                if (v := dims.get(dim))
            }
            for task, dims in per_task.items()
        }
    return out
