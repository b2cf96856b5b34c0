"""Reports: the folder's files, Markdown tables that match the scores, escaping, highlighting, parse status,
the figures' content, determinism, missing inputs, the CLI; and `compare` between runs and models."""

from __future__ import annotations

import json
import re
import shutil

import pytest
from PIL import Image

from report_helpers import CONDS, EVIL, NEGATED_FINAL, add_model, make_run, score_synthetic, shared_report
from scoring_helpers import prefill_embeddings
from vlmproprio.report import ReportError, compare_runs, load_run_scores, write_report
from vlmproprio.report.page import highlight
from vlmproprio.report.tables import fmt_p, fmt_paired, fmt_value, parsing_table

for _module in ("matplotlib", "jinja2"):
    pytest.importorskip(_module, reason="reports need the [report] extra: pip install 'vlmproprio[report]'")

PLOTS = (
    "fig5_success__synthetic.png",
    "fig6_points__synthetic.png",
    "f1_threshold__synthetic.png",
    "fig7_trace_door_00__synthetic.png",
    "fig8_trace_bin0_00__synthetic.png",
    "power_curves.png",
)


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """The run and its report, shared with test_report_browser.py (built once per session; read only here)."""
    return shared_report(tmp_path_factory)


@pytest.fixture(scope="module")
def run(shared):
    return shared[0]


@pytest.fixture(scope="module")
def page(shared):
    index = shared[1]
    return index, index.read_text(encoding="utf-8")


def _md_row(md: str, *cells: str) -> list[str]:
    prefix = "| " + " | ".join(cells) + " |"
    rows = [line for line in md.splitlines() if line.startswith(prefix)]
    assert rows, f"no row starting {prefix!r}"
    return [c.strip() for c in rows[0].strip("|").split(" | ")]


# ---------------------------------------------------------------------------------------------- files


def test_report_folder_has_page_markdown_plots_and_thumbnails(run, page):
    index, text = page
    out = index.parent
    assert index == run[0] / "report" / "index.html"
    assert (out / "report.md").is_file()
    for name in PLOTS:
        with Image.open(out / name) as im:
            assert im.format == "PNG" and im.width > 600
            lo, hi = im.convert("L").getextrema()
            assert hi - lo > 100, f"{name} looks blank"
        assert f'src="{name}"' in text
    thumbs = sorted((out / "frames").glob("*.jpg"))
    assert thumbs, "no frame thumbnails"
    with Image.open(thumbs[0]) as im:
        assert im.format == "JPEG" and max(im.size) <= 128
    # every image the page uses is a file inside the report folder: the folder can be copied as it is
    for src in re.findall(r'<img src="([^"]+)"', text):
        assert not src.startswith(("/", "http:", "https:", "file:")), src
        assert (out / src).is_file(), src
    assert (out / "index.html").stat().st_mode & 0o044, "report files must be readable by others"


def test_power_section_uses_the_runs_episodes_and_corrected_alpha(run, page):
    """The minimal detectable effects shown are vlmproprio.power's for this run's episodes per task, at alpha over
    the number of primary hypotheses it was scored against."""
    from vlmproprio import power
    from vlmproprio.report.data import load_run_scores
    from vlmproprio.report.power_section import run_groups

    s = load_run_scores(run[0])
    groups = run_groups(s)
    assert groups["all"] == sum(v for k, v in groups.items() if k != "all") == len({r["episode_id"] for r in s.rows})
    n_primary = len(s.verdicts["claims"]["primary"])
    level = power.PowerSettings(alpha=s.verdicts["claims"]["alpha"], family=n_primary).level
    md = (page[0].parent / "report.md").read_text(encoding="utf-8")
    assert f"= {level:.4f}" in md
    for g, n in groups.items():
        mde = power.rate_mde(n, 0.0, level)
        assert _md_row(md, g, str(n))[2] == ("never" if mde is None else f"{mde:.2f}")


def test_markdown_tables_show_the_scores(run, page):
    md = (page[0].parent / "report.md").read_text(encoding="utf-8")
    scores = load_run_scores(run[0])
    assert "prompt version: test" in md  # read from the model's pipeline settings in run.json
    # the template captions: with state every item is right, without it the trajectory is never mentioned
    both = _md_row(md, "synthetic", "all", "both")
    none = _md_row(md, "synthetic", "all", "none")
    header = next(line for line in md.splitlines() if line.startswith("| model | task | condition | n |"))
    cols = [c.strip() for c in header.strip("|").split(" | ")]
    assert both[cols.index("all correct")] == "100%" and none[cols.index("trajectory mentioned")] == "0%"
    agg = scores.aggregate_row("synthetic", "door", "ee")
    ee = _md_row(md, "synthetic", "door", "ee")
    assert ee[cols.index("words")] == fmt_value("final_words", agg["final_words"])
    seg_header = next(line for line in md.splitlines() if "| LOO thr |" in line)
    seg_cols = [c.strip() for c in seg_header.strip("|").split(" | ")]
    seg = [line for line in md.splitlines() if line.startswith("| synthetic | door | ee |") and line != "|"][1]
    seg = [c.strip() for c in seg.strip("|").split(" | ")]
    assert seg[seg_cols.index("F1 LOO")] == fmt_value("seg_loo_f1_tol1", agg["seg_loo_f1_tol1"])
    assert seg[seg_cols.index("F1 lift")] == fmt_value("seg_loo_f1_tol1_lift", agg["seg_loo_f1_tol1_lift"])
    assert seg[seg_cols.index("chance F1")] == fmt_value("seg_loo_f1_tol1_chance", agg["seg_loo_f1_tol1_chance"])
    assert "best thr" not in seg_cols  # the in-sample best is no table column
    # paired differences vs none, with CI and p-value, as in scores/paired.json
    p = next(
        r
        for r in scores.paired
        if (r["task"], r["metric"], r["a"], r["b"]) == ("all", "final_trajectory_correct", "both", "none")
    )
    assert p["mean_diff"] == 1.0
    row = _md_row(md, "synthetic", "all", "both − none")
    assert fmt_paired("final_trajectory_correct", p) in row
    p_header = next(line for line in md.splitlines() if line.startswith("| model | task | A − B | n | object correct"))
    p_cols = [c.strip() for c in p_header.strip("|").split(" | ")]
    # all correct in 7 of 7 episodes with state, 0 without: exact sign-flip p = 2/2**7
    # exploratory: with its Benjamini-Hochberg q-value
    q = fmt_p(
        next(
            r
            for r in scores.paired
            if (r["task"], r["metric"], r["a"], r["b"]) == ("all", "final_all_correct", "both", "none")
        )["q_bh"]
    )
    assert row[p_cols.index("all correct")] == f"+100 pp [+100, +100] p=0.016 q={q}"
    # the primary hypothesis carries a star and its Holm-adjusted p
    assert row[p_cols.index("trajectory correct")].startswith("★ +100 pp [+100, +100] p=0.016 Holm p=")
    # the verdicts come first: the combined claims, then one line per primary hypothesis, before the run facts
    lines = md.splitlines()
    assert lines[2] == "## Verdicts"
    verdict_lines = [x for x in lines[: lines.index("## Tables")] if x.startswith("- synthetic — ")]
    claims = [x for x in verdict_lines if x.startswith("- synthetic — CLAIM ")]
    assert len(claims) == len(scores.verdicts["combined"]) >= 2 and verdict_lines[: len(claims)] == claims
    assert len(verdict_lines) - len(claims) == len(scores.verdicts["verdicts"]) >= 3
    assert "- synthetic — trajectory_both_vs_none: both > none on final_trajectory_correct (all): inconclusive" in md
    # how strong each control is: its states' correlation with the true ones, from meta.json
    controls = scores.meta["controls"]["both_shuffled"]["door"]
    ctrl = _md_row(md, "both_shuffled", "door")
    c_header = next(line for line in md.splitlines() if line.startswith("| condition | task | joints 1–7 |"))
    c_cols = [c.strip() for c in c_header.strip("|").split(" | ")]
    assert ctrl[c_cols.index("z")] == f"{controls['z']['mean_r']:+.2f}"
    assert "| synthetic | all | both − both_shuffled |" in md
    for name in PLOTS:
        assert f"]({name})" in md


# ---------------------------------------------------------------------------------------------- page content


def test_parsing_recoveries_per_model(run, page):
    md = (page[0].parent / "report.md").read_text(encoding="utf-8")
    assert "### Parsing recoveries" in md
    # written transcripts, no model answers: one frame made 'recovered' by hand, one missing, nothing heavy
    assert _md_row(md, "synthetic", "0")[1:] == ["0", "0 (0 chars)", "1", "1", "0 (0%)", "–"]
    scores = load_run_scores(run[0])
    frames = {"captions": 10, "recovered": 4, "missing": 2, "heavy": 2}
    counts = {"label": {"frames": 2, "scenes": 0, "final": 0}, "quotes": {"frames": 0, "scenes": 3, "final": 1}}
    model = {"answers": 5, "answers_with_reasoning": 2, "reasoning_chars": 80, "frames": frames, "recoveries": counts}
    scores.meta = {**scores.meta, "parsing": {"heavy_classes": ["unnumbered"], "models": {"m": model}}}
    table = parsing_table(scores)
    assert table.rows == [["m", "5", "2 (80 chars)", "4", "2", "2 (25%)", "label 2/0/0; quotes 0/3/1"]]
    scores.meta = {k: v for k, v in scores.meta.items() if k != "parsing"}  # scored before it was kept
    assert parsing_table(scores) is None


def test_caption_text_is_escaped(page):
    _, text = page
    escaped = EVIL.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&#34;")
    assert text.count(escaped) == 2  # the frame caption and the final caption, as text
    assert "<img src=x" not in text and '<script>document.title="pwned"' not in text
    assert text.count("<script>") == 1  # the page's own


def test_rubric_spans_are_highlighted_with_their_lexicon_entry(run, page):
    _, text = page
    audit = load_run_scores(run[0]).audit
    fin = audit["synthetic/door_01__ee"]["final"]
    assert fin["text"].startswith(NEGATED_FINAL)
    neg = next(m for m in fin["matches"] if m["negated"])
    assert (neg["text"], neg["verdict"]) == ("open", "wrong")
    marks = re.findall(r'<mark class="([^"]+)" title="([^"]*)">([^<]*)</mark>', text)
    assert any(c == "hit v-wrong negated" and w == "open" and neg["entry"] in t for c, t, w in marks)
    far = next(m for m in audit["synthetic/bin3_00__both"]["final"]["matches"] if m["text"] == "far")
    assert any(c == "hit v-correct" and w == "far" and far["entry"] in t for c, t, w in marks)
    assert {c for c, _, _ in marks} >= {"hit v-correct", "hit v-ignored", "hit v-wrong negated"}


def test_parse_status_of_every_caption_is_visible(run, page):
    _, text = page
    statuses = re.findall(r'<span class="caption status-(\w+)"><span class="status">(\w+)</span>', text)
    assert statuses and all(a == b for a, b in statuses)
    counts = {s: sum(1 for a, _ in statuses if a == s) for s in ("ok", "recovered", "missing")}
    # one recovered frame + one recovered scene; one missing frame (door_00 both, frame 3)
    assert counts["recovered"] == 2 + 1  # the legend shows one of each
    assert counts["missing"] == 1 + 1
    assert counts["ok"] > 100


def test_page_has_every_episode_frames_and_metadata(run, page):
    _, text = page
    _, _, ids = run
    for eid in ids:
        assert f'id="ep-synthetic-{eid}"' in text
    assert text.count('<details class="episode"') == len(ids)
    assert text.index('id="ep-synthetic-door_00" open') > 0  # the first episode is open
    assert text.count('loading="lazy"') == sum(14 if e.startswith("door") else 11 for e in ids) - 14
    assert "scores/meta.json" in text and "fake-encoder" in text
    for c in CONDS:
        assert f"<th>{c}</th>" in text


def test_highlight_keeps_text_and_skips_bad_offsets():
    text = "move left and up"
    matches = [
        {"start": 5, "end": 9, "text": "left", "verdict": "correct", "entry": "e1"},
        {"start": 6, "end": 12, "text": "eft an", "verdict": "wrong", "entry": "e2"},  # overlaps: left out
        {"start": 14, "end": 16, "text": "up", "verdict": "mentioned", "negated": True, "entry": "e3"},
        {"start": 10, "end": 99, "text": "x", "verdict": "correct"},  # outside the text
        {"start": 0, "end": 4, "text": "MOVE", "verdict": "correct"},  # not this text
    ]
    spans = highlight(text, matches)
    assert "".join(s.text for s in spans) == text
    assert [(s.text, s.style) for s in spans if s.style] == [
        ("left", "hit v-correct"),
        ("up", "hit v-mentioned negated"),
    ]
    assert "e3" in spans[-1].tooltip and "negated" in spans[-1].tooltip


# ---------------------------------------------------------------------------------------------- figures


def test_success_rates_figure_draws_mentioned_and_correct_bars(run):
    from vlmproprio.report.plots import success_rates_figure

    s = load_run_scores(run[0])
    fig = success_rates_figure(s, "synthetic")
    door, bins = fig.axes[:2]
    assert "Door" in door.get_title() and "Bin" in bins.get_title()
    # per condition: 3 mentioned bars then 3 correct bars, in condition order
    heights = [p.get_height() for p in door.patches]
    assert len(heights) == 2 * 3 * len(CONDS)
    per_cond = {c: heights[6 * i : 6 * i + 6] for i, c in enumerate(s.conditions)}
    agg = s.aggregate_row("synthetic", "door", "none")
    assert per_cond["none"][2] == pytest.approx(100 * agg["final_trajectory_mentioned"]) == 0.0
    assert per_cond["both"][3:] == pytest.approx([100.0, 100.0, 100.0])


def test_trace_figure_has_threshold_and_the_caption_at_each_point(run):
    from vlmproprio.report.plots import trace_figure
    from vlmproprio.transcripts import read_transcripts

    s = load_run_scores(run[0])
    captions = {
        t.condition: [f.text for f in t.frames]
        for t in read_transcripts(run[0])
        if t.episode_id == "door_01" and t.condition in ("none", "both")
    }
    fig = trace_figure(s, "synthetic", "door_01", ["none", "both"], captions)
    _, ax_both = fig.axes
    assert any(ln.get_ydata()[0] == 0.65 and ln.get_linestyle() == "--" for ln in ax_both.get_lines())
    pred = s.traces["synthetic/door_01__both"]["predicted_boundaries"]
    assert pred, "the template captions change at the phase changes"
    texts = [a.get_text() for a in ax_both.texts]
    assert len(texts) == len(pred)
    for j, t in zip(pred, texts, strict=True):
        assert " ".join(t.split())[:30] == captions["both"][j + 1][:30]
    assert f"{len(pred)} segmentation point(s) at 0.65" in ax_both.get_title(loc="left")


# ---------------------------------------------------------------------------------------------- behaviour


def test_report_is_deterministic(run, page, tmp_path):
    write_report(run[0], out=tmp_path / "again")
    first = page[0].parent
    names = sorted(p.relative_to(first).as_posix() for p in first.rglob("*") if p.is_file())
    assert names == sorted(
        p.relative_to(tmp_path / "again").as_posix() for p in (tmp_path / "again").rglob("*") if p.is_file()
    )
    for name in names:
        assert (first / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name


def test_without_fixtures_the_page_says_so_and_a_wrong_folder_is_an_error(run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy, ignore=shutil.ignore_patterns("report"))
    manifest = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**manifest, "fixtures": str(tmp_path / "gone")}))
    text = write_report(copy).read_text(encoding="utf-8")
    assert "Frames are not shown" in text and "gone" in text
    assert not (copy / "report" / "frames").exists() or not any((copy / "report" / "frames").iterdir())
    with pytest.raises(ReportError, match="not found"):
        write_report(copy, fixtures=tmp_path / "nowhere")


def test_unscored_or_stale_runs_are_errors(run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy, ignore=shutil.ignore_patterns("report"))
    src = copy / "transcripts" / "synthetic" / "door_00__none.json"
    shutil.copy(src, src.with_name("door_00__joint.json"))
    with pytest.raises(ReportError, match=r"out of date.*door_00__joint"):
        write_report(copy)
    shutil.rmtree(copy / "scores")
    with pytest.raises(ReportError, match="score the run first"):
        write_report(copy)


def test_cli_report_scores_an_unscored_run_first(run, tmp_path, capsys, monkeypatch):
    from vlmproprio.cli import main
    from vlmproprio.embeddings import default_embedding_dir, encoder_spec

    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path / "cache"))  # fake vectors stay out of the session cache
    copy = tmp_path / "run"
    shutil.copytree(run[0], copy, ignore=shutil.ignore_patterns("report", "scores", "embeddings"))
    prefill_embeddings(
        copy, encoder_spec().key, default_embedding_dir()
    )  # the default encoder's vectors: scoring needs no torch
    assert main(["report", str(copy), "--examples", "door_02", "--trace-conditions", "ee,both"]) == 0
    out = capsys.readouterr().out
    assert "scored" in out and f"report: {copy / 'report' / 'index.html'}" in out
    assert (copy / "scores" / "aggregate.json").is_file()
    assert sorted(p.name for p in (copy / "report").glob("fig7*.png")) == ["fig7_trace_door_02__synthetic.png"]
    assert not list((copy / "report").glob("fig8*.png"))
    assert main(["report", str(copy), "--examples", "door_99"]) == 2
    assert "door_99" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "missing")]) == 2


# ---------------------------------------------------------------------------------------------- compare


@pytest.fixture(scope="module")
def two_models(tmp_path_factory):
    """One run, two models: 'beta' is 'alpha' with the no-state final caption under 'both'."""
    run, _, ids = make_run(tmp_path_factory.mktemp("compare"), model="alpha", score=False)
    add_model(run, "alpha", "beta", {"both": "none"})
    score_synthetic(run)
    return run, ids


def _find(comparison, **match):
    return next(r for r in comparison.rows if all(r[k] == v for k, v in match.items()))


def test_compare_two_models_in_one_run(two_models):
    run, ids = two_models
    c = compare_runs(run, model_a="alpha", model_b="beta")
    r = _find(c, task="all", condition="both", metric="final_trajectory_correct")
    assert (r["n"], r["a"], r["b"], r["diff"]) == (len(ids), 1.0, 0.0, -1.0)
    assert r["p_value"] == 2 / 2 ** len(ids) and r["ci_low"] == r["ci_high"] == -1.0
    same = _find(c, task="door", condition="ee", metric="final_words")
    assert same["diff"] == 0.0 and same["p_value"] == 1.0
    md = c.to_markdown()
    assert "| all | both | trajectory correct | 7 | 100% | 0% | -100 pp [-100, -100] | 0.016 |" in md
    with pytest.raises(ReportError, match="--model-a and --model-b"):
        compare_runs(run, model_a="alpha")
    with pytest.raises(ReportError, match="no model 'gamma'"):
        compare_runs(run, model_a="alpha", model_b="gamma")


def test_compare_two_runs_matches_rows_on_model(two_models, tmp_path, capsys):
    from vlmproprio.cli import main

    run, _ = two_models
    other = tmp_path / "other"
    shutil.copytree(run, other)
    c = compare_runs(run, other)
    assert {r["model"] for r in c.rows} == {"alpha", "beta"}
    assert all(r["diff"] in (0.0, None) for r in c.rows)
    assert "| model | task |" in c.to_markdown()
    out = tmp_path / "cmp.md"
    assert (
        main(
            [
                "compare",
                str(run),
                str(other),
                "--task",
                "door",
                "--metrics",
                "final_words,seg_f1_tol1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    text = out.read_text(encoding="utf-8")
    assert text in printed and "| alpha | door | both | words |" in text and "| all |" not in text
    assert main(["compare", str(run), str(other), "--metrics", "nonsense"]) == 2
    assert "unknown metric" in capsys.readouterr().err


def test_compare_single_model_runs_with_different_names(run, two_models):
    c = compare_runs(run[0], two_models[0], model_b="alpha")
    assert _find(c, task="all", condition="both", metric="final_all_correct")["diff"] == 0.0
    with pytest.raises(ReportError, match="no model in common"):
        compare_runs(run[0], two_models[0])


def test_power_analyses_are_kept_in_the_given_cache_and_never_in_the_fixtures(run, tmp_path, monkeypatch):
    import vlmproprio.power as P

    write_report(run[0], out=tmp_path / "r1", cache_dir=tmp_path / "cache")
    assert (tmp_path / "cache" / P.POWER_CACHE_DIR / "cache.db").is_file()
    monkeypatch.setattr(P, "analyse", lambda *a, **k: pytest.fail("computed again"))
    write_report(run[0], out=tmp_path / "r2", cache_dir=tmp_path / "cache")  # read back
    assert (tmp_path / "r1" / "index.html").read_bytes() == (tmp_path / "r2" / "index.html").read_bytes()
    monkeypatch.undo()
    fixtures = shutil.copytree(run[1], tmp_path / "fixtures")
    before = sorted(fixtures.rglob("*"))
    write_report(run[0], fixtures, out=tmp_path / "r3", cache_dir=fixtures / "cache")  # a cache inside the fixtures
    assert sorted(fixtures.rglob("*")) == before
