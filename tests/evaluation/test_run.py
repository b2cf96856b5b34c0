"""Scoring a whole run: the tables, missing captions, bit-identical replay, no torch when cached, CLI, judge."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

from scoring_helpers import fake_spec, prefill_embeddings, write_synthetic_run
from vlmproprio.answering import Answerer
from vlmproprio.backends.base import Backend
from vlmproprio.cache import key_identity, request_key
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.embeddings import EmbeddingError
from vlmproprio.evaluation import ScoreRunError, score_run
from vlmproprio.segmentation import THRESHOLDS

SRC = Path(__file__).resolve().parents[2] / "src"
TESTS = Path(__file__).resolve().parents[1]
CONDS = ("none", "ee", "both", "both_shuffled")
MISSING = {("door_00", "both"): [3, 4], ("bin2_00", "none"): [0]}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("run")
    run, fx = base / "run", base / "fixtures"
    ids = write_synthetic_run(run, fx, n_door=3, n_per_bin=1, n_frames=14, conditions=CONDS, missing=MISSING)
    prefill_embeddings(run, fake_spec().key)
    return run, ids


@pytest.fixture(scope="module")
def tables(small_run):
    run, _ = small_run
    return score_run(run, encoder=fake_spec())


def _rows(tables, **match):
    return [r for r in tables.rows if all(r[k] == v for k, v in match.items())]


def test_one_row_per_transcript_with_every_metric(tables, small_run):
    _, ids = small_run
    assert len(tables.rows) == len(ids) * len(CONDS)
    r = _rows(tables, episode_id="door_00", condition="both")[0]
    for col in (
        "final_words",
        "final_hits_per_word",
        "final_trajectory_correct",
        "scene_action_mentioned",
        "seg_points",
        "seg_f1_tol0",
        "seg_f1_tol1",
        "seg_f1_tol2",
        "seg_edit",
        "seg_gt_boundaries",
    ):
        assert col in r, col
    assert [c["condition"] for c in _rows(tables, episode_id="bin0_00")] == list(CONDS)


def test_rubric_results_of_the_template_captions(tables):
    for r in _rows(tables, condition="none"):
        assert (r["final_object_correct"], r["final_action_correct"], r["final_trajectory_mentioned"]) == (1, 1, 0)
    for r in _rows(tables, condition="both"):
        assert r["final_all_correct"] == 1, r["episode_id"]
        assert r["final_words"] > 10


def test_missing_frames_stay_in_place(tables):
    r = _rows(tables, episode_id="door_00", condition="both")[0]
    assert r["frames_missing"] == 2 and r["n_frames"] == 14
    tr = tables.traces["synthetic/door_00__both"]
    assert len(tr["trace"]) == 13
    assert tr["trace"][2] is None and tr["trace"][3] is None and tr["trace"][4] is None
    assert tr["frame_status"][3] == "missing" and tr["trace"][5] is not None
    assert not set(tr["predicted_boundaries"]) & {2, 3, 4}
    assert _rows(tables, episode_id="bin2_00", condition="none")[0]["frames_missing"] == 1


def test_template_captions_segment_at_the_true_boundaries(tables):
    # frame captions repeat their phase's template, so the fake embeddings change exactly at phase changes
    r = _rows(tables, episode_id="door_01", condition="none")[0]
    assert r["seg_f1_tol0"] == 1.0 and r["seg_edit"] == 100.0


def test_sweep_has_every_threshold_and_more_points_higher(tables):
    rows = [s for s in tables.sweep if s["episode_id"] == "bin1_00" and s["condition"] == "ee"]
    assert [s["threshold"] for s in rows] == list(THRESHOLDS)
    points = [s["points"] for s in rows]
    assert points == sorted(points) and points[-1] > points[0]
    agg = [a for a in tables.sweep_aggregate if a["task"] == "all" and a["condition"] == "ee"]
    assert len(agg) == len(THRESHOLDS) and agg[0]["n_episodes"] == 7


def test_aggregate_and_paired_tables(tables):
    door_none = next(a for a in tables.aggregate if (a["task"], a["condition"]) == ("door", "none"))
    assert door_none["n_episodes"] == 3 and door_none["final_action_correct"] == 1.0
    assert "seg_best_threshold" not in door_none  # an in-sample choice is no score (only the sweep shows it)
    pairs = {(p["task"], p["metric"], p["a"], p["b"]): p for p in tables.paired}
    p = pairs[("all", "final_trajectory_correct", "both", "none")]
    assert p["n"] == 7 and p["mean_diff"] == 1.0 and p["p_value"] == 2 / 2**7
    assert ("door", "final_words", "both", "both_shuffled") in pairs
    assert ("door", "final_words", "both_shuffled", "none") in pairs


def test_audit_shows_why(tables):
    a = tables.audit["synthetic/bin3_00__both"]
    assert a["expectation"]["target_row"] == "far" and a["expectation"]["target_side"] == "left"
    m = {h["text"]: h for h in a["final"]["matches"]}
    assert m["far"]["verdict"] == "correct" and a["final"]["items"]["trajectory"]["correct"]
    assert len(a["scenes"]) == 3 and a["scenes"][0]["frame_indices"] == [0, 1, 2, 3, 4]


def test_meta_names_encoder_and_lexicons(tables):
    meta = tables.meta
    assert meta["encoder"]["name"] == "fake-encoder" and meta["encoder"]["revision"] == "test-1"
    assert meta["encoder"]["dim"] == 16 and "path" not in meta["encoder"] and "threads" not in meta["encoder"]
    assert set(meta["lexicons"]) == {"door", "pick_place"}


def test_written_files_are_valid_json_and_csv(tables, small_run):
    run, _ = small_run
    out = run / "scores"
    for name in ("rows", "aggregate", "sweep", "sweep_aggregate", "paired"):
        data = json.loads((out / f"{name}.json").read_text())
        lines = (out / f"{name}.csv").read_text().splitlines()
        assert len(lines) == len(data) + 1
    assert json.loads((out / "meta.json").read_text())["scores_version"] == 2


def test_score_run_writes_the_per_frame_table_into_its_stamped_generation(tables, small_run):
    """Every caller of score_run (the score command, the benchmark, the inspect task) gets frames.csv."""
    import csv

    from vlmproprio.evaluation import check_scores
    from vlmproprio.evaluation.frame_table import COLUMNS

    run, _ = small_run
    with (run / "scores" / "frames.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == COLUMNS
    assert len(rows) == sum(r["n_frames"] for r in tables.rows)
    assert "frames.csv" in check_scores(run, ["frames.csv"])["files"]  # one generation with the score files


def _score_files(run: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((run / "scores").iterdir()) if p.name != "timing.json"}


SUBPROCESS = """
import sys, json
sys.path.insert(0, {tests!r})
from vlmproprio.evaluation import score_run
from vlmproprio.embeddings import encoder_spec
from scoring_helpers import fake_spec
spec = fake_spec() if {fake!r} else encoder_spec()
t = score_run({run!r}, encoder=spec)
heavy = sorted(m for m in ("torch", "transformers", "sentence_transformers") if m in sys.modules)
print(json.dumps({{"heavy": heavy, "computed": t.timing["embeddings"]["computed"]}}))
"""


def _run_scoring_subprocess(run: Path, fake: bool) -> dict:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}
    code = SUBPROCESS.format(tests=str(TESTS), run=str(run), fake=fake)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_scores_are_bit_identical_across_runs_and_processes(tables, small_run):
    run, _ = small_run
    first = _score_files(run)
    score_run(run, encoder=fake_spec())
    assert _score_files(run) == first
    assert _run_scoring_subprocess(run, fake=True) == {"heavy": [], "computed": 0}
    assert _score_files(run) == first


def test_a_cached_run_imports_no_torch(tmp_path, monkeypatch):
    """The default encoder's spec (name, revision) and the whole scoring path, with torch never imported."""
    from vlmproprio.embeddings import encoder_spec  # light: the spec names the files, loads nothing

    run, fx = tmp_path / "run", tmp_path / "fx"
    write_synthetic_run(run, fx, n_door=1, n_per_bin=1, n_frames=10, conditions=("none", "both"))
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))  # the subprocess inherits it
    prefill_embeddings(run, encoder_spec().key, tmp_path / "cache" / "embeddings")
    assert _run_scoring_subprocess(run, fake=False) == {"heavy": [], "computed": 0}


def test_uncached_text_with_unloadable_encoder_is_a_clean_error(tmp_path):
    run, fx = tmp_path / "run", tmp_path / "fx"
    write_synthetic_run(run, fx, n_door=1, n_per_bin=0, n_frames=8, conditions=("none",))
    with pytest.raises(EmbeddingError, match="encoder folder not found"):
        score_run(run, encoder=fake_spec())


def test_bad_run_dirs_are_clean_errors(tmp_path):
    with pytest.raises(ScoreRunError, match="not found"):
        score_run(tmp_path / "nope", encoder=fake_spec())
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScoreRunError, match="no transcripts"):
        score_run(tmp_path / "empty", encoder=fake_spec())


def test_cli_score(small_run, capsys):
    from vlmproprio.cli import main
    from vlmproprio.embeddings import encoder_spec

    run, _ = small_run
    cache = run.parent / "cli-cache"
    # --embedding-cache names the cache root; the vectors live in its embeddings/ folder. Prefilled there, the
    # command scores with no encoder loaded (prefilled in the root itself, it loaded and ran the real one).
    prefill_embeddings(run, encoder_spec().key, cache_dir=cache / "embeddings")
    assert main(["score", str(run), "--embedding-cache", str(cache)]) == 0
    out = capsys.readouterr().out
    assert "scored 28 transcripts" in out
    assert ", 0 computed)" in out  # every vector came from the --embedding-cache given
    assert "verdict synthetic: trajectory_both_vs_none: both > none on final_trajectory_correct (all): " in out
    assert main(["score", str(run.parent / "missing")]) == 2
    assert "run directory not found" in capsys.readouterr().err
    assert main(["score", str(run), "--embedding-cache", str(cache), "--workers", "2"]) == 0
    assert "scored 28 transcripts" in capsys.readouterr().out
    for bad in ("0", "two"):
        assert main(["score", str(run), "--workers", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--workers must be a whole number of worker processes" in err[0], err


class RuleJudge(Backend):
    """A fake judge: says everything is mentioned, and correct only when the caption says 'toward' or 'far'."""

    max_batch_size = 4

    def __init__(self):
        self.seen: list[ChatRequest] = []

    def identity(self) -> dict[str, str]:
        return {"backend": "fake-judge", "model_id": "rule"}

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        assert len(requests) <= self.max_batch_size
        self.seen.extend(requests)
        out = []
        for r in requests:
            caption = r.messages[-1].text.split('"""')[1]
            ok = "toward" in caption or "far" in caption
            items = {k: {"mentioned": True, "correct": ok} for k in ("object", "action", "trajectory")}
            text = "Sure! " + json.dumps(items) if "bin0" not in r.tag.episode_id else "I cannot tell."
            out.append(Answer(text, AnswerMeta(backend="fake-judge", model_id="rule")))
        return out


def test_judge_scorer_reports_agreement_with_the_rubric(small_run):
    run, ids = small_run
    judge = RuleJudge()
    t = score_run(run, encoder=fake_spec(), judge=Answerer(judge, mode="live"), write=False)
    # judge requests are content-addressed like captioning's: a caption judged against the same ground
    # truth is asked once, whichever episode or condition it came from
    assert len(t.judge["verdicts"]) == len(ids) * len(CONDS)
    keys = [request_key(key_identity(judge.identity()), r) for r in judge.seen]
    assert len(keys) == len(set(keys)) and 0 < len(keys) < len(ids) * len(CONDS)
    assert "Ground truth" in judge.seen[0].messages[-1].text and judge.seen[0].tag.stage == "judge"
    agr = t.judge["agreement"]
    assert agr["n"] == 28 and agr["unparsed"] == len(CONDS)  # bin0_00 answers are not JSON
    # the rubric says object mentioned everywhere, so the judge agrees on that item every time
    assert agr["items"]["object_mentioned"]["agreement"] == 1.0
    # it marks every 'none' caption's trajectory mentioned, the rubric does not
    tm = agr["items"]["trajectory_mentioned"]
    assert 0.0 < tm["agreement"] < 1.0 and tm["n"] == 24
    assert math.isfinite(agr["items"]["trajectory_correct"]["kappa"])
    v = t.judge["verdicts"]["synthetic/bin0_00__none"]
    assert v["items"] is None and "no JSON" in v["error"]


def test_aggregate_snapshot(tables, data_regression):
    """The whole-run means of the template run, frozen: any change to lexicons or metrics shows up here."""
    rows = [a for a in tables.aggregate if a["task"] == "all"]
    data_regression.check({"aggregate_all_tasks": rows})


@pytest.mark.slow
def test_real_encoder_cold_then_warm_in_another_process_is_bit_identical(tmp_path, monkeypatch):
    pytest.importorskip("sentence_transformers")  # the [embed] extra
    from vlmproprio.embeddings import encoder_spec

    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))  # cold: a cache of its own

    run, fx = tmp_path / "run", tmp_path / "fx"
    write_synthetic_run(run, fx, n_door=1, n_per_bin=1, n_frames=9, conditions=("none", "both"))
    cold = score_run(run, encoder=encoder_spec())
    assert cold.timing["embeddings"]["computed"] == cold.timing["embeddings"]["requested"] > 0
    first = _score_files(run)
    assert _run_scoring_subprocess(run, fake=False) == {"heavy": [], "computed": 0}
    assert _score_files(run) == first
    meta = json.loads(first["meta.json"])
    assert meta["encoder"]["name"] == "sentence-transformers/all-MiniLM-L6-v2" and meta["encoder"]["dim"] == 384
    # real sentence similarities: a caption is most like its own phase's neighbours
    tr = cold.traces["synthetic/door_00__both"]
    assert all(x is not None and -1.0 <= x <= 1.0 for x in tr["trace"])
    across = [x for j, x in enumerate(tr["trace"]) if j in tr["true_boundaries"]]
    within = [x for j, x in enumerate(tr["trace"]) if j not in tr["true_boundaries"]]
    assert sum(within) / len(within) > sum(across) / len(across)


# ---------------------------------------------------------------------------------------------- out of sample, chance


def test_out_of_sample_threshold_is_chosen_on_the_other_episodes(tables):
    """Recompute leave-one-episode-out from the sweep table: the held-out episode never picks its own threshold."""
    sweep_by = {}
    for s in tables.sweep:
        sweep_by.setdefault((s["model"], s["task"], s["condition"], s["episode_id"]), {})[s["threshold"]] = s
    for r in tables.rows:
        others = [
            v
            for (m, t, c, e), v in sweep_by.items()
            if (m, t, c) == (r["model"], r["task"], r["condition"]) and e != r["episode_id"]
        ]
        if not others:
            assert r["seg_loo_threshold"] is None
            continue
        means = {thr: sum(o[thr]["f1_tol1"] for o in others) / len(others) for thr in THRESHOLDS}
        best = max(means.values())
        want = min(thr for thr, v in means.items() if math.isclose(v, best, rel_tol=0, abs_tol=1e-12))
        assert r["seg_loo_threshold"] == want
        own = sweep_by[(r["model"], r["task"], r["condition"], r["episode_id"])][want]
        assert r["seg_loo_f1_tol1"] == own["f1_tol1"] and r["seg_loo_points"] == own["points"]


def test_chance_columns_and_lift(tables):
    from vlmproprio.segmentation import chance_random, truth_of

    r = _rows(tables, episode_id="door_00", condition="ee")[0]
    labels = tables.traces["synthetic/door_00__ee"]["true_phases"]
    want = chance_random(truth_of(labels), r["seg_loo_points"])
    assert r["seg_loo_f1_tol1_chance"] == want["f1_tol1"]
    assert r["seg_loo_f1_tol1_lift"] == r["seg_loo_f1_tol1"] - want["f1_tol1"]
    assert r["seg_loo_edit_lift"] == r["seg_loo_edit"] - want["edit"]
    for col in ("seg_f1_tol1_even", "seg_loo_f1_at_50_chance", "seg_groups_f1_tol1", "seg_groups_points"):
        assert isinstance(r[col], float), col
    chance = tables.meta["segmentation"]["chance"]
    assert chance["group_size"] == 5 and 0 <= chance["exact_share"] <= 1


def test_paired_rows_are_primary_or_exploratory_with_corrected_p(tables, small_run):
    from vlmproprio.verdicts import load_claims

    claims = load_claims()
    primary = [p for p in tables.paired if p["family"] == "primary"]
    assert {p["hypothesis"] for p in primary} == {h.id for h in claims.hypotheses if h.b in CONDS}
    for p in primary:
        assert p["p_holm"] >= p["p_value"] and p["q_bh"] is None
    expl = [p for p in tables.paired if p["family"] == "exploratory"]
    assert len(expl) + len(primary) == len(tables.paired)
    assert all(p["q_bh"] is None or p["q_bh"] >= p["p_value"] for p in expl)
    from vlmproprio.stats import holm

    assert [p["p_holm"] for p in primary] == holm([p["p_value"] for p in primary])
    v = {x["hypothesis"]: x for x in tables.verdicts["verdicts"]}
    # the template captions name the trajectory only with state: 7 of 7 episodes, p = 2/2**7 = 0.016 < 0.05,
    # but the family has four hypotheses, so Holm's correction leaves it inconclusive
    traj = v["trajectory_both_vs_none"]
    assert traj["p_value"] == 2 / 2**7 and traj["mean_diff"] == 1.0
    assert traj["p_holm"] > 0.05 and traj["verdict"] == "inconclusive"
    csv_header = (small_run[0] / "scores" / "paired.csv").read_text().splitlines()[0].split(",")
    assert {"family", "hypothesis", "p_holm", "q_bh"} <= set(csv_header)


# ---------------------------------------------------------------------------------------------- workers


def _spy_parts(monkeypatch) -> dict[str, list[int]]:
    """Into how many processes' chunks each parallel map of this test was cut (none: one loop here), by what it
    maps (transcripts: the cells; score files: their texts)."""
    import vlmproprio.parallel as parallel

    parts: dict[str, list[int]] = {}

    def spy(fn, items, chunks, what):
        parts.setdefault(what, []).append(len(chunks))
        return real(fn, items, chunks, what)

    real = parallel._run
    monkeypatch.setattr(parallel, "_run", spy)
    return parts


def test_any_number_of_workers_gives_the_same_score_files(small_run, monkeypatch):
    """Missing frames and scenes, one model: cut down to one episode per worker."""
    run, _ = small_run
    monkeypatch.setattr("vlmproprio.evaluation.cells.MIN_CELLS_PER_WORKER", 1)
    parts = _spy_parts(monkeypatch)
    files = {}
    for workers in (1, 3, 28):
        score_run(run, encoder=fake_spec(), workers=workers)
        files[workers] = _score_files(run)
    assert parts["transcripts"] == [3, 7]  # 7 episodes: at most 7 chunks (an episode's cells stay together)
    assert parts["score files"] == [3, 3]  # 15 files, at least 4 per worker
    assert files[3] == files[1] and files[28] == files[1]


def test_the_cells_scored_by_workers_equal_those_of_one_loop(small_run, monkeypatch):
    """Everything score_cells returns, the sanity checks' inputs too (which rarely change a score file)."""
    from vlmproprio.evaluation import embed_captions, load_run_inputs, score_cells

    run, _ = small_run
    monkeypatch.setattr("vlmproprio.evaluation.cells.MIN_CELLS_PER_WORKER", 1)
    inputs = load_run_inputs(run, None, True)
    captions = embed_captions(inputs, fake_spec(), None, None)
    one = score_cells(inputs, captions, THRESHOLDS, 0.65)
    assert one.outputs["synthetic"].frames_missing == 3  # the planted gaps: the comparison below can see them
    for workers in (2, 5, 28):
        assert score_cells(inputs, captions, THRESHOLDS, 0.65, workers) == one, workers


def test_the_shipped_fixtures_score_the_same_with_two_workers(tmp_path, monkeypatch):
    """Real captions of two models and both tasks, at the default chunk size."""
    from vlmproprio.cli import main

    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))
    run = tmp_path / "run"
    episodes = "door_05,bin0_00,bin3_01"
    for model in ("reference", "reference-state"):
        args = ["run", "--model", model, "--mode", "replay", "--episodes", episodes, "--conditions", "all"]
        assert main([*args, "--out", str(run), "--no-progress"]) == 0
    parts = _spy_parts(monkeypatch)
    files = {}
    for workers in (1, 2):
        score_run(run, workers=workers)
        files[workers] = _score_files(run)
    assert parts == {"transcripts": [2], "score files": [2]}  # 54 transcripts of 3 episodes: two chunks
    assert files[2] == files[1]
