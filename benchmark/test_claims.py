"""The paper's claims as gates, per model and task (expectations in benchmark/claims.yml).

A claim "A beats B on metric M" holds on a task when, paired by episode, the mean difference A - B is
positive and its p-value (exact sign-flip / permutation test, vlmproprio.stats) is below ``alpha``.
The test fails whenever the observed outcome differs from the recorded expectation, in either direction,
so what a model shows can never change silently.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

CLAIMS = yaml.safe_load((Path(__file__).parent / "claims.yml").read_text())


def _observed(paired: list[dict], slug: str, task: str, spec: dict) -> dict:
    for r in paired:
        if (r["model"], r["task"], r["metric"], r["a"], r["b"]) == (slug, task, spec["metric"], spec["a"], spec["b"]):
            return r
    raise LookupError(f"no paired comparison {spec['a']} vs {spec['b']} on {spec['metric']} for {slug}/{task}")


def holds(row: dict, alpha: float) -> bool:
    return row["mean_diff"] > 0 and row["p_value"] < alpha


@pytest.mark.parametrize("claim", list(CLAIMS["claims"]))
def test_paper_claim(bench_model, bench_session, claim: str) -> None:
    from vlmproprio.backends.registry import model_slug
    from vlmproprio.episodes import list_episode_ids

    spec = CLAIMS["claims"][claim]
    if set(bench_model.episodes) != set(list_episode_ids(bench_session.fixtures)):
        pytest.skip("the claims are judged on every episode of the fixtures; run without --episodes")
    missing = {spec["a"], spec["b"]} - set(bench_model.conditions)
    if missing:
        pytest.skip(f"claim {claim} needs condition(s) {', '.join(sorted(missing))} (see --conditions)")
    slug = model_slug(bench_model.name)
    alpha = CLAIMS["alpha"]
    observed = {task: _observed(bench_model.paired, slug, task, spec) for task in ("door", "pick_place", "all")}
    summary = "; ".join(
        f"{t}: diff {r['mean_diff']:+.3f} [{r['ci_low']:+.3f}, {r['ci_high']:+.3f}] p={r['p_value']:.4f} "
        f"-> {'holds' if holds(r, alpha) else 'does not hold'}"
        for t, r in observed.items()
    )
    expected = CLAIMS["expected"].get(bench_model.name, {}).get(claim)
    if expected is None:
        pytest.skip(f"no expectation recorded in benchmark/claims.yml for {bench_model.name}; observed {summary}")
    wrong = [t for t, exp in expected.items() if holds(observed[t], alpha) != exp]
    assert not wrong, (
        f"{bench_model.name}: claim '{claim}' ({spec['description']}) differs from benchmark/claims.yml on "
        f"{', '.join(wrong)}. Observed {summary}. If the change is meant, update the expectation."
    )
