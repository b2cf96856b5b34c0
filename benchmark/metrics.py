"""What the regression gates compare, per (model, episode, condition) cell.

Counts, booleans and keyword hits are compared exactly (YAML baselines); every float is compared with
FLOAT_TOLERANCE (CSV baselines); which metric is gated how is a column of the metric table
(vlmproprio.evaluation.metrics.METRICS). Only what depends on the cell alone is gated here: the out-of-sample
(leave-one-episode-out) segmentation depends on the other episodes of the task, so it is judged by
benchmark/test_claims.py on whole runs, not per cell. Replay from cassettes is bit-identical, so a difference is a real
change: of the pipeline, the prompts, the parser, the lexicons, the encoder or the model's answers.
"""

from __future__ import annotations

import re
from pathlib import Path

from vlmproprio.evaluation.metrics import METRICS, gated_metrics

BASELINES = Path(__file__).parent / "baselines"
# absolute and relative tolerance for float metrics (rates, F1, similarities)
FLOAT_TOLERANCE = {"atol": 1e-6, "rtol": 1e-6}


def baseline_path(model_slug: str, episode_id: str, condition: str, suffix: str) -> Path:
    return BASELINES / model_slug / episode_id / f"{condition}{suffix}"


def exact_metrics(row: dict, sweep: list[dict]) -> dict:
    """The exactly gated metrics of the metric table, nested by their ``gate_key``, and the points per threshold."""
    out: dict = {}
    for spec in METRICS:
        if spec.gated == "exact":
            *groups, key = spec.gate_key.split(".")
            node = out
            for g in groups:
                node = node.setdefault(g, {})
            node[key] = row[spec.name]
    out["segmentation"]["points_per_threshold"] = {f"{r['threshold']:.2f}": r["points"] for r in sweep}
    return out


def _float(value) -> float:
    """Undefined metrics (e.g. a similarity when every caption is missing) are stored as None: NaN here,
    and NaN equals NaN in num_regression."""
    return float("nan") if value is None else float(value)


def float_metrics(row: dict) -> dict[str, list[float]]:
    """The metric table's metrics gated within FLOAT_TOLERANCE, in its order (the CSV baseline's columns)."""
    return {n: [_float(row[n])] for n in gated_metrics("float")}


def sweep_metrics(sweep: list[dict]) -> dict[str, list[float]]:
    cols = ("threshold", "p_tol1", "r_tol1", "f1_tol0", "f1_tol1", "f1_tol2", "edit", "f1_at_10", "f1_at_25")
    cols += ("f1_at_50", "frame_acc", "edit_unmerged")
    return {c: [_float(r[c]) for r in sweep] for c in cols}


# What pytest-regressions writes, and nothing that pandas might read otherwise: plain names; numbers without sign
# '+', spaces, '_' or quotes; an empty cell (NaN to pandas); integers short enough for int64
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")
_NUMBER = re.compile(r"(?:-?(?:\d+\.\d+(?:[eE][-+]?\d+)?|\d+[eE][-+]?\d+|\d{1,18}))?")
_INDEX = re.compile(r"\d{1,18}")


def _plainly_numeric_csv(path: Path, columns: list[str] | None) -> bool:
    """True only for a CSV that pandas surely reads as ``columns`` (any order), all numeric: a file as
    pytest-regressions writes it. False means "not sure", never "damaged": pandas then decides, and words the
    problem. Reading every baseline with pandas here cost about as much as pytest-regressions' own reads."""
    try:
        text = path.read_bytes().decode("ascii")
    except (OSError, UnicodeDecodeError):
        return False
    lines = text.split("\n")
    if lines[-1] == "":
        lines.pop()  # the final newline
    if len(lines) < 2 or '"' in text or "\r" in text:
        return False
    header = lines[0].split(",")
    names = header[1:]
    if header[0] != "" or not names or len(set(names)) != len(names) or not all(_NAME.fullmatch(n) for n in names):
        return False
    if columns is not None and sorted(names) != sorted(columns):
        return False
    for line in lines[1:]:
        cells = line.split(",")
        if len(cells) != len(header) or not _INDEX.fullmatch(cells[0]):
            return False
        if not all(_NUMBER.fullmatch(c) for c in cells[1:]):
            return False
    return True


def baseline_problem(path: Path, columns: list[str] | None = None) -> str | None:
    """Why a baseline file cannot be compared (one line naming it), or None when it can or does not exist yet
    (pytest-regressions then writes it). A damaged file would otherwise end in a long pandas or YAML traceback
    without the file's name."""
    if not path.is_file():
        return None
    fix = f"restore it (`git checkout -- {path}`) or regenerate it with --force-regen"
    try:
        if path.suffix == ".csv":
            if _plainly_numeric_csv(path, columns):
                return None
            import pandas as pd

            frame = pd.read_csv(path, index_col=0)
            if columns is not None and sorted(frame.columns) != sorted(columns):
                return (
                    f"{path}: damaged baseline (columns {list(frame.columns)[:4]}..., expected {columns[:4]}...); {fix}"
                )
            # the dtypes, not frame[c]: building a Series per column cost more than reading the file
            bad = [c for c, dtype in frame.dtypes.items() if not pd.api.types.is_numeric_dtype(dtype)]
            if bad:
                return f"{path}: damaged baseline (column {bad[0]!r} is not numeric); {fix}"
        else:
            import yaml

            # libyaml's safe loader when PyYAML has it (the same documents, 8x faster than the pure-Python one)
            loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
            if not isinstance(yaml.load(path.read_text(encoding="utf-8"), Loader=loader), dict):
                return f"{path}: damaged baseline (not a YAML mapping); {fix}"
    except Exception as exc:  # any parser error: the point is one line naming the file
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        return f"{path}: damaged baseline ({type(exc).__name__}: {first}); {fix}"
    return None
