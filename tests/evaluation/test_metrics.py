"""The metric table (vlmproprio.evaluation.metrics): every reader's list of metrics is derived from it, and a
metric added as one row with its function reaches every reader."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from scoring_helpers import fake_spec, prefill_embeddings, write_synthetic_run
from vlmproprio.evaluation import CAPTION_METRICS, FINAL_TOTALS, PAIRED_METRICS, metrics, score_run
from vlmproprio.evaluation.metrics import (
    DOC_END,
    DOC_START,
    METRICS,
    CellView,
    MetricSpec,
    caption_metrics,
    compare_metrics,
    final_totals,
    gated_metrics,
    headline_metrics,
    markdown_table,
    paired_metrics,
    primary_metrics,
    report_columns,
    segmentation_paired,
)
from vlmproprio.report import compare, tables
from vlmproprio.verdicts import load_claims

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmark.metrics import exact_metrics, float_metrics  # noqa: E402


def _exclamations(view: CellView) -> int:
    return view.transcript.final.count("!")


# a metric as one would add it: a row and its function
EXTRA = MetricSpec(
    "final_exclamations",
    "exclamations",
    "count",
    "caption",
    paired=True,
    gated="float",
    compare=True,
    report="captions",
    compute=_exclamations,
)


def test_names_are_unique_and_exact_gates_have_a_key():
    assert len({m.name for m in METRICS}) == len(METRICS)
    assert all(m.gate_key for m in METRICS if m.gated == "exact")
    assert not [m.name for m in METRICS if m.gate_key and m.gated != "exact"]


def test_every_reader_derives_its_list_from_the_table():
    assert paired_metrics() == PAIRED_METRICS
    assert caption_metrics() == CAPTION_METRICS
    assert final_totals() == FINAL_TOTALS
    assert report_columns("captions") == tables.CAPTION_COLUMNS
    assert report_columns("segmentation") == tables.SEGMENTATION_COLUMNS
    assert headline_metrics() == tables.HEADLINE_METRICS
    assert compare_metrics() == compare.COMPARE_METRICS
    row = {m.name: i for i, m in enumerate(METRICS)}  # a distinct value per column
    assert tuple(float_metrics(row)) == gated_metrics("float")
    gated = exact_metrics(row, [])
    assert {m.name: _leaf(gated, m.gate_key) for m in METRICS if m.gated == "exact"} == {
        n: row[n] for n in gated_metrics("exact")
    }


def _leaf(tree: dict, key: str):
    for part in key.split("."):
        tree = tree[part]
    return tree


@pytest.mark.skipif(importlib.util.find_spec("inspect_ai") is None, reason="needs the inspect extra")
def test_the_inspect_scorers_report_the_paired_metrics():
    from vlmproprio import inspect as task

    assert caption_metrics() == task.RUBRIC_METRICS
    assert tuple(m.replace("seg_loo_", "seg_") for m in segmentation_paired()) == task.SEGMENTATION_METRICS


def test_labels_and_units_are_the_tables():
    for m in METRICS:
        assert (tables.label(m.name), tables.metric_kind(m.name)) == (m.label, m.unit), m.name


def test_primary_flags_are_the_packaged_pre_registration():
    assert set(primary_metrics()) == {h.metric for h in load_claims().hypotheses}


def test_the_docs_show_the_table():
    text = (ROOT / "docs" / "metrics.md").read_text(encoding="utf-8")
    expected = f"{DOC_START}\n\n{markdown_table()}\n{DOC_END}"
    assert expected in text, "docs/metrics.md's metric table is out of date: run `python scripts/metric_table.py`"


def test_an_added_metric_reaches_every_list():
    table = (*METRICS, EXTRA)
    for listed in (
        paired_metrics(table),
        caption_metrics(table),  # the inspect caption scorer's
        final_totals(table),
        compare_metrics(table),
        report_columns("captions", table),
        gated_metrics("float", table),
    ):
        assert listed[-1] == "final_exclamations"
    assert "| `final_exclamations` | exclamations | count | caption | yes | float |" in markdown_table(table)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("run")
    run = base / "run"
    write_synthetic_run(run, base / "fixtures", n_door=2, n_per_bin=1, n_frames=10, conditions=("none", "both"))
    prefill_embeddings(run, fake_spec().key)
    return run


def test_an_added_metric_function_fills_its_column(small_run, monkeypatch):
    monkeypatch.setattr(metrics, "METRICS", (*METRICS, replace(EXTRA, compute=lambda v: len(v.frame_status))))
    scored = score_run(small_run, encoder=fake_spec())
    assert all(r["final_exclamations"] == r["n_frames"] for r in scored.rows)
    assert all(a["final_exclamations"] == a["n_frames"] for a in scored.aggregate)


def test_the_table_as_shipped_adds_no_column(small_run):
    scored = score_run(small_run, encoder=fake_spec())
    assert "final_exclamations" not in scored.rows[0]
