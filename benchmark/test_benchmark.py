"""The benchmark: regression gates per (model, episode, condition).

Run ``pytest benchmark/ --model NAME``; update baselines with ``--force-regen`` after a change you mean.
Each gate is its own test so that one ``--force-regen`` run rewrites all of a cell's baselines.
"""

from __future__ import annotations

import pytest

from benchmark.metrics import (
    FLOAT_TOLERANCE,
    baseline_path,
    baseline_problem,
    exact_metrics,
    float_metrics,
    sweep_metrics,
)


def _usable(config, path, columns=None):
    if config.getoption("force_regen", False):
        return path  # being rewritten: a damaged one is what --force-regen replaces
    problem = baseline_problem(path, columns)
    if problem:
        pytest.fail(problem, pytrace=False)
    return path


def _slug(cell) -> str:
    return cell.cell.model.slug


def test_counts(bench_cell, data_regression, pytestconfig) -> None:
    """Parse statuses, word counts, keyword hits, rubric verdicts, segmentation points: exact."""
    c = bench_cell.cell
    data_regression.check(
        exact_metrics(bench_cell.row, bench_cell.sweep),
        fullpath=_usable(pytestconfig, baseline_path(_slug(bench_cell), c.episode_id, c.condition, ".yml")),
    )


def test_rates(bench_cell, num_regression, pytestconfig) -> None:
    """Scene-caption rates, keyword hits per word, boundary P/R/F1, edit score, similarities: tolerance."""
    c = bench_cell.cell
    values = float_metrics(bench_cell.row)
    num_regression.check(
        values,
        fullpath=_usable(
            pytestconfig, baseline_path(_slug(bench_cell), c.episode_id, c.condition, ".rates.csv"), list(values)
        ),
        default_tolerance=FLOAT_TOLERANCE,
    )


def test_threshold_sweep(bench_cell, num_regression, pytestconfig) -> None:
    """Boundary P/R/F1 and edit score at every threshold 0.00..1.00: tolerance."""
    c = bench_cell.cell
    values = sweep_metrics(bench_cell.sweep)
    num_regression.check(
        values,
        fullpath=_usable(
            pytestconfig, baseline_path(_slug(bench_cell), c.episode_id, c.condition, ".sweep.csv"), list(values)
        ),
        default_tolerance=FLOAT_TOLERANCE,
    )
