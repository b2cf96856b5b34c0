"""The verdict gates, per model (expectations in benchmark/claims.yml, hypotheses in vlmproprio/claims.yml).

For every pre-registered primary hypothesis the verdict of the model's scored run (Holm-corrected within the
model's primary family, vlmproprio.verdicts) must equal the one recorded; the model's sanity warnings must be
the ones recorded. Either direction of a change fails, so what a model shows can never change silently.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from vlmproprio.verdicts import format_combined, format_verdict, load_claims

EXPECTED = yaml.safe_load((Path(__file__).parent / "claims.yml").read_text())
CLAIMS = load_claims()


def _verdicts(bench_model) -> dict:
    return json.loads((bench_model.run_dir / "scores" / "verdicts.json").read_text())


def _require_full_run(bench_model, bench_session) -> None:
    from vlmproprio.episodes import list_episode_ids

    if set(bench_model.episodes) != set(list_episode_ids(bench_session.fixtures)):
        pytest.skip("the verdicts are judged on every episode of the fixtures; run without --episodes")


def test_expectations_name_known_hypotheses() -> None:
    ids = {h.id for h in CLAIMS.hypotheses} | {c.id for c in CLAIMS.combined}
    for model, exp in EXPECTED["expected"].items():
        assert set(exp) <= ids, f"benchmark/claims.yml: {model} names unknown hypotheses {set(exp) - ids}"
        assert set(exp.values()) <= {"supported", "not supported", "inconclusive"}, model


def _skip_unless_judgeable(bench_model, bench_session, key: str, conditions: set[str]) -> None:
    """Skip when the run cannot judge ``key`` (a hypothesis or a combined claim): not every episode, or a
    condition it needs was not run."""
    _require_full_run(bench_model, bench_session)
    missing = conditions - set(bench_model.conditions)
    if missing:
        pytest.skip(f"{key} needs condition(s) {', '.join(sorted(missing))} (see --conditions)")


def _expected_or_skip(bench_model, key: str, observed: str) -> str:
    """The verdict benchmark/claims.yml expects of the model on ``key``; skips with the observed one when none is."""
    expected = EXPECTED["expected"].get(bench_model.name, {}).get(key)
    if expected is None:
        pytest.skip(f"no expectation in benchmark/claims.yml for {bench_model.name}; observed {observed}")
    return expected


def _assert_verdict(bench_model, got: dict, expected: str, text: str) -> None:
    assert got["verdict"] == expected, (
        f"{bench_model.name}: {text}; benchmark/claims.yml expects '{expected}'. "
        "If the change is meant, update the expectation."
    )


def _mine(bench_model, section: str, field: str, key: str) -> dict:
    slug = bench_model.model.slug
    return next(v for v in _verdicts(bench_model)[section] if v["model"] == slug and v[field] == key)


@pytest.mark.parametrize("hypothesis", [h.id for h in CLAIMS.hypotheses])
def test_primary_verdict(bench_model, bench_session, hypothesis: str) -> None:
    h = next(h for h in CLAIMS.hypotheses if h.id == hypothesis)
    _skip_unless_judgeable(bench_model, bench_session, hypothesis, {h.a, h.b})
    got = _mine(bench_model, "verdicts", "hypothesis", hypothesis)
    text = format_verdict(got)
    expected = _expected_or_skip(bench_model, hypothesis, text)
    # no verdict of the fixtures may rest on sampled sign patterns: up to 40 pairs the test is exact
    assert got["p_method"] == "exact sign-flip", text
    _assert_verdict(bench_model, got, expected, text)


@pytest.mark.parametrize("claim", [c.id for c in CLAIMS.combined])
def test_combined_claim(bench_model, bench_session, claim: str) -> None:
    """The combined claims (both > none AND both > both_shuffled, ...) are gated like the hypotheses under them."""
    c = next(c for c in CLAIMS.combined if c.id == claim)
    needed = {x for h in CLAIMS.hypotheses if h.id in c.all_of for x in (h.a, h.b)}
    _skip_unless_judgeable(bench_model, bench_session, claim, needed)
    got = _mine(bench_model, "combined", "claim", claim)
    text = format_combined(got)
    _assert_verdict(bench_model, got, _expected_or_skip(bench_model, claim, text), text)


def test_sanity_warnings(bench_model, bench_session) -> None:
    _require_full_run(bench_model, bench_session)
    expected = EXPECTED["warnings"].get(bench_model.name)
    warnings = _verdicts(bench_model)["warnings"]
    kinds = sorted(w["kind"] for w in warnings)
    if expected is None:
        pytest.skip(f"no warnings recorded in benchmark/claims.yml for {bench_model.name}; observed {kinds}")
    assert kinds == sorted(expected), (
        f"{bench_model.name}: warnings {kinds} but benchmark/claims.yml expects {sorted(expected)}: "
        + "; ".join(w["message"] for w in warnings)
    )
    if {"gibberish", "off-task", "state-echo", "near-constant"} & set(kinds):
        # a model flagged as unreadable must not have a supported claim
        assert not [v for v in _verdicts(bench_model)["verdicts"] if v["verdict"] == "supported"]
