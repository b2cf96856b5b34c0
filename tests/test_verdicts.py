"""Verdicts: the claims file, family marking with Holm / BH, the verdict rule, and the sanity warnings --
on hand-made inputs and on the shipped models' replayed captions (the tiny random model must be flagged, the
reference captioner must not be flagged as gibberish or near-constant)."""

from __future__ import annotations

from pathlib import Path

import pytest

from vlmproprio.sanity import ModelOutputs, group_edge_excess, non_word_share, sanity_warnings
from vlmproprio.stats import benjamini_hochberg, holm, paired_difference
from vlmproprio.verdicts import (
    VERDICT_RULES,
    ClaimsError,
    effect_bound,
    format_verdict,
    load_claims,
    mark_families,
    verdict_of,
    verdicts,
)

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"


def test_packaged_claims_are_a_small_primary_family():
    c = load_claims()
    assert c.alpha == 0.05 and 2 <= len(c.hypotheses) <= 6
    ids = {h.id for h in c.hypotheses}
    assert {"trajectory_both_vs_none", "boundary_lift_both_vs_none", "trajectory_both_vs_shuffled"} <= ids
    assert all(h.task in ("door", "pick_place", "all") for h in c.hypotheses)
    # every primary metric is one evaluation pairs
    from vlmproprio.evaluation import PAIRED_METRICS

    assert {h.metric for h in c.hypotheses} <= set(PAIRED_METRICS)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("alpha: 0.05\n", "non-empty 'primary'"),
        ("alpha: 2\nprimary: {h: {description: d, metric: m, a: x, b: y}}\n", "alpha must be"),
        ("primary: {h: {description: d, metric: m, a: x}}\n", r"primary.h: missing b"),
        ("primary: {h: {description: d, metric: m, a: x, b: y, side: left}}\n", "unknown key"),
        ("primary: [\n", "cannot read"),
    ],
)
def test_bad_claims_files_are_one_line_errors(tmp_path, text, match):
    p = tmp_path / "claims.yml"
    p.write_text(text)
    with pytest.raises(ClaimsError, match=match):
        load_claims(p)


def _row(model, metric, a, b, p, d=0.1, lo=-0.1, hi=0.3, task="all"):
    return {"model": model, "task": task, "metric": metric, "a": a, "b": b, "p_value": p, "mean_diff": d,
            "ci_low": lo, "ci_high": hi, "n": 22}  # fmt: skip


def test_mark_families_corrects_primary_with_holm_and_the_rest_with_bh_per_model(tmp_path):
    p = tmp_path / "claims.yml"
    p.write_text(
        "alpha: 0.05\nprimary:\n"
        "  h1: {description: d, metric: m1, a: both, b: none}\n"
        "  h2: {description: d, metric: m2, a: both, b: none}\n"
    )
    claims = load_claims(p)
    rows = [
        _row("x", "m1", "both", "none", 0.01),
        _row("x", "m2", "both", "none", 0.04),
        _row("x", "m1", "both", "none", 0.001, task="door"),  # not the primary task: exploratory
        _row("x", "m3", "both", "none", 0.02),
        _row("y", "m1", "both", "none", 0.03),
    ]
    mark_families(rows, claims)
    assert [r["family"] for r in rows] == ["primary", "primary", "exploratory", "exploratory", "primary"]
    assert [rows[0]["p_holm"], rows[1]["p_holm"]] == holm([0.01, 0.04])  # 0.02, 0.04
    assert [rows[2]["q_bh"], rows[3]["q_bh"]] == benjamini_hochberg([0.001, 0.02])
    assert rows[4]["p_holm"] == 0.03  # model y: its own family of one
    v = verdicts(rows, claims, ["x", "y"])
    assert [x["verdict"] for x in v] == ["supported", "supported", "supported", "not tested"]


@pytest.mark.parametrize(
    ("d", "p_holm", "hi", "want"),
    [
        (0.2, 0.01, 0.4, "supported"),
        (0.2, 0.05, 0.4, "supported"),
        (0.2, 0.06, 0.4, "inconclusive"),
        (0.0, 1.0, 0.0, "not supported"),  # CI [0, 0]: no positive effect detected (a bound is stated)
        (-0.1, 0.2, 0.05, "inconclusive"),
        (-0.2, 0.01, -0.1, "not supported"),
    ],
)
def test_verdict_rule(d, p_holm, hi, want):
    assert verdict_of({"mean_diff": d, "p_holm": p_holm, "ci_high": hi}, 0.05) == want
    assert verdict_of(None, 0.05) == "not tested"


def test_not_supported_states_the_largest_compatible_effect():
    """No discordant pair among 22 episodes: the bootstrap CI is [0, 0], yet up to +15.4 pp is compatible."""
    row = paired_difference([0.0] * 22, [0.0] * 22, binary=True).to_dict()
    row["p_holm"] = 1.0
    assert (row["ci_low"], row["ci_high"]) == (0.0, 0.0)
    assert verdict_of(row, 0.05) == "not supported"
    bound, text = effect_bound(row)
    assert bound == pytest.approx(1 - 0.025 ** (1 / 22), rel=1e-12) and 0.15 < bound < 0.16
    assert text == "no effect above +15.4 pp detected (exact 95 % bound; 0 vs 0 discordant of 22 episodes)"
    # a continuous metric states the bootstrap CI's upper end instead
    cont = {"mean_diff": 0.01, "ci_high": 0.07, "p_holm": 0.4}
    assert effect_bound(cont) == (0.07, "no effect above +0.070 detected (bootstrap 95 % CI)")
    assert set(VERDICT_RULES) == {"supported", "not supported", "inconclusive", "not tested"}


def test_verdicts_carry_the_bound_and_the_test_method():
    claims = load_claims()
    h = next(h for h in claims.hypotheses if h.metric == "final_trajectory_correct")
    res = paired_difference([1.0] * 2 + [0.0] * 20, [0.0] * 22, binary=True)
    row = {"model": "m", "task": h.task, "metric": h.metric, "a": h.a, "b": h.b, **res.to_dict()}
    mark_families([row], claims)
    (v,) = [v for v in verdicts([row], claims, ["m"]) if v["hypothesis"] == h.id]
    assert v["verdict"] == "inconclusive" and v["p_method"] == "exact sign-flip"
    assert (v["exact_low"], v["exact_high"]) == (res.exact_low, res.exact_high)
    assert v["bound"] == res.exact_high and "2 vs 0 discordant of 22" in v["bound_text"]
    assert format_verdict(v).endswith("; " + v["bound_text"])


def test_binomial_tail_equals_scipy():
    from scipy.stats import binomtest

    from vlmproprio.sanity import binomial_tail

    for k, n, p in [(4, 4, 0.2), (0, 10, 0.3), (340, 1194, 0.188), (3, 50, 0.01), (50, 50, 0.5), (1, 1, 0.999)]:
        assert binomial_tail(k, n, p) == pytest.approx(binomtest(k, n, p, alternative="greater").pvalue, rel=1e-9)


def test_non_words_and_group_edges():
    assert non_word_share(["The robot moves 0.25 m up.", "x1y2 ### ok"]) == (pytest.approx(2 / 9), 9)
    # repeated texts (a model's captions across conditions) count every time they occur, as one pass over all
    texts = ["x1y2 ### ok", None, "The robot moves 0.25 m up.", "x1y2 ### ok", "", "x1y2 ### ok", None]
    assert non_word_share(texts) == (6 / 15, 15)
    # two 11-frame cells, k = 5: edges at 4 and 9 (2 of 10 positions)
    g = group_edge_excess([(11, [4, 9]), (11, [4, 9])], 5)
    assert (g["on_edges"], g["points"], g["expected"]) == (4, 4, pytest.approx(0.8))
    assert g["p_value"] == pytest.approx(0.2**4)
    assert group_edge_excess([(11, [1, 2, 6, 7])], 5)["on_edges"] == 0


def test_sanity_warnings_fire_on_made_up_outputs():
    good = ModelOutputs(
        frame_captions=[f"the arm moves {i} cm left" for i in range(100)],
        cell_distinct=[0.9] * 10,
        all_captions=["the arm moves left"] * 10,
        final_hits=[2] * 10,
        cells=[(11, [2]), (11, [6])],
        frames_heavy=19,  # 19 % of the present captions placed by position: under the limit
    )
    bad = ModelOutputs(
        frame_captions=["zq\x04xx"] * 100,
        cell_distinct=[0.1] * 8 + [0.2] * 2,
        frames_missing=300,
        frames_heavy=20,  # 20 % of the 100 present ones (the 300 missing ones do not dilute it)
        all_captions=["zq\x04xx ��a"] * 10,
        final_hits=[0] * 10,
        cells=[(11, [4, 9])] * 20,
    )
    w = sanity_warnings({"good": good, "bad": bad}, 5)
    assert {x["kind"] for x in w if x["model"] == "bad"} == {
        "near-constant",
        "missing-captions",
        "gibberish",
        "off-task",
        "group-edges",
        "heavy-recovery",
    }
    heavy = next(x for x in w if x["kind"] == "heavy-recovery")
    assert heavy["value"] == pytest.approx(0.2) and "20 of 100 present frame captions" in heavy["message"]
    assert not [x for x in w if x["model"] == "good"]


def _replayed_outputs(models: tuple[str, ...], tmp_path: Path) -> dict[str, ModelOutputs]:
    """Each model's captions from its committed cassette / rules (no embeddings needed), all from one replay run
    (as `vlmproprio run --model a,b,c`: the fixtures are loaded and verified once, not once per model)."""
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.runner import RunPlan, run
    from vlmproprio.scoring import expectation_for, load_lexicon, score_text
    from vlmproprio.transcripts import read_transcripts

    out = tmp_path / "replay"
    runs = run(RunPlan(models=models, conditions=tuple(parse_conditions("all")), fixtures=FIXTURES, out=out,
                       mode="replay", progress=False))  # fmt: skip
    eps = {e.episode_id: e for e in load_episodes(FIXTURES)}
    outputs = {}
    for r in runs:
        o = outputs[r.model.name] = ModelOutputs()
        for t in read_transcripts(out, r.model.slug):
            lex = load_lexicon(t.task)
            present = [f.text for f in t.frames if f.status != "missing" and f.text.strip()]
            o.frames_heavy += sum(1 for f in t.frames if f.status != "missing" and f.text.strip() and _heavy(f))
            o.frame_captions += present
            o.cell_distinct.append(len(set(present)) / len(t.frames))
            o.frames_missing += len(eps[t.episode_id].frames) - len(present)
            o.all_captions += [*present, *(s.text for s in t.scenes), t.final]
            o.final_hits.append(score_text(t.final, expectation_for(eps[t.episode_id], lex), lex).hits)
    return outputs


def _heavy(f) -> bool:
    from vlmproprio.parsing import HEAVY_CLASSES

    return bool(HEAVY_CLASSES.intersection(f.removed))


def test_tiny_random_model_is_flagged_and_the_reference_captioner_is_not(tmp_path):
    outputs = _replayed_outputs(("reference", "reference-state", "tiny-qwen2-vl"), tmp_path)
    assert list(outputs) == ["reference", "reference-state", "tiny-qwen2-vl"]
    from vlmproprio.conditions import CONDITIONS

    assert all(len(o.cell_distinct) == 22 * len(CONDITIONS) for o in outputs.values())  # every cell, per model
    w = sanity_warnings(outputs, 5)
    kinds = {m: {x["kind"] for x in w if x["model"] == m} for m in outputs}
    # its few readable answers are unnumbered lines the parser placed by position
    assert {"gibberish", "near-constant", "heavy-recovery"} <= kinds["tiny-qwen2-vl"]
    for readable in ("reference", "reference-state"):  # templated, but every episode's captions follow its input
        assert not kinds[readable] & {"gibberish", "near-constant", "missing-captions", "heavy-recovery"}, readable


def test_captions_made_of_numbers_are_a_state_echo_not_gibberish():
    """A model that echoes the state writes numbers: every token is a number (0 % non-words), and its final
    captions name nothing the rubric knows. That is 'state-echo', with the share of numbers said, never 'gibberish'
    nor the generic 'off-task'."""
    echo = ModelOutputs(
        frame_captions=[f"{i * 0.01:.3f} -0.512 1.204 {i}" for i in range(100)],
        cell_distinct=[0.9] * 10,
        all_captions=[f"{i * 0.01:.3f} -0.512 1.204 {i}" for i in range(10)],
        final_hits=[0] * 10,
        cells=[(11, [2]), (11, [6])],
    )
    w = {x["kind"]: x for x in sanity_warnings({"echo": echo}, 5)}
    assert "gibberish" not in w and "off-task" not in w
    assert w["state-echo"]["number_share"] == 1.0 and "100% of caption tokens are numbers" in w["state-echo"]["message"]


def test_an_untested_hypothesis_says_why_and_prints_no_nan():
    claims = load_claims()
    h = claims.hypotheses[0]
    undefined = {
        "model": "m",
        "task": h.task,
        "metric": h.metric,
        "a": h.a,
        "b": h.b,
        "n": 0,
        "mean_diff": float("nan"),
        "ci_low": float("nan"),
        "ci_high": float("nan"),
        "p_value": float("nan"),
    }
    mark_families([undefined], claims)
    got = {v["hypothesis"]: v for v in verdicts([undefined], claims, ["m"])}
    lines = [format_verdict(v) for v in got.values()]
    assert all(v["verdict"] == "not tested" for v in got.values())
    assert not [x for x in lines if "nan" in x.lower()], lines
    assert f"no episode has a value of {h.metric} under both {h.a} and {h.b}" in format_verdict(got[h.id])
    other = claims.hypotheses[-1]
    assert f"no paired comparison of {other.a} with {other.b}" in format_verdict(got[other.id])
