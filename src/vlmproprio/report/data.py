"""What a report reads: the score tables of a run (RUN_DIR/scores/), its run.json and transcripts, its episodes.

Everything is read from files written by the run and score commands; nothing is recomputed
here, so a report always shows the numbers the scores hold.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import load_required_json
from vlmproprio.transcripts import cell_key

SCORES_DIR = "scores"
# the score files a report needs; sweep.json (per episode) is left out: the plots use the means
SCORE_FILES = ("rows", "aggregate", "sweep_aggregate", "paired", "audit", "traces", "meta", "verdicts")
TASKS_FILE = "tasks.json"  # labels and paper figures of tasks, as data (report/tasks.json)


@cache
def _task_table() -> dict[str, dict]:
    raw = resources.files("vlmproprio").joinpath("report", TASKS_FILE).read_text()
    try:
        tasks = json.loads(raw)["tasks"]
        return {str(t): dict(v) for t, v in tasks.items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ReportError(f"vlmproprio/report/{TASKS_FILE}: malformed ({exc!r})") from exc


def task_label(task: str | None) -> str:
    """The report's name of a task ("Door opening"); a task report/tasks.json does not list is named from its
    own name ("nut_assembly" -> "Nut assembly")."""
    if not task:
        return ""
    entry = _task_table().get(task)
    return str(entry["label"]) if entry and "label" in entry else task.replace("_", " ").capitalize()


def paper_figure(task: str | None) -> int | None:
    """The number of the paper's figure that shows this task's segmentation traces, None for a task it has not."""
    entry = _task_table().get(task or "") or {}
    return int(entry["paper_figure"]) if "paper_figure" in entry else None


def task_order(tasks: set[str]) -> list[str]:
    """Tasks in report order: the paper's first (by figure), the listed ones next in their file order, then any
    other in name order; "all" is not a task and is left out."""
    listed = [t for t in _task_table() if t in tasks and t != "all"]
    listed.sort(key=lambda t: (paper_figure(t) is None, paper_figure(t) or 0))
    return listed + sorted(tasks - set(listed) - {"all"})


class ReportError(VlmproprioError):
    """A run directory that cannot be reported on; the message names the file and what to do."""


@dataclass
class RunScores:
    """The score tables of one run, as written by vlmproprio.evaluation.write_score_tables."""

    run_dir: Path
    manifest: dict
    rows: list[dict]
    aggregate: list[dict]
    sweep_aggregate: list[dict]
    paired: list[dict]
    audit: dict
    traces: dict
    meta: dict
    verdicts: dict = field(default_factory=dict)  # scores/verdicts.json: claims, verdicts, sanity warnings
    models: list[str] = field(default_factory=list)
    conditions: list[str] = field(default_factory=list)
    episodes: list[str] = field(default_factory=list)
    judge: dict | None = None  # scores/judge.json, when the run was scored with --judge

    @property
    def threshold(self) -> float:
        return float(self.meta.get("segmentation", {}).get("default_threshold", 0.65))

    def tasks(self, with_all: bool = False) -> list[str]:
        present = {r["task"] for r in self.rows}
        tasks = task_order(present)
        return [*tasks, "all"] if with_all and len(tasks) > 1 else tasks

    @property
    def pooled_task(self) -> str:
        """The task name of every episode together: "all", or the one task of a run that has only one (the
        scores write an "all" row only for two tasks or more)."""
        tasks = self.tasks(with_all=True)
        return "all" if "all" in tasks or not tasks else tasks[0]

    def task_of(self, episode_id: str) -> str | None:
        return next((r["task"] for r in self.rows if r["episode_id"] == episode_id), None)

    def aggregate_row(self, model: str, task: str, condition: str) -> dict | None:
        return next(
            (a for a in self.aggregate if (a["model"], a["task"], a["condition"]) == (model, task, condition)), None
        )

    @property
    def prompt_version(self) -> str | None:
        """The models' prompt versions ("suite-2"; several joined by ", "), None if run.json names none."""
        models = [m for m in self.manifest.get("models", []) if isinstance(m, dict)]
        found = {m.get("pipeline", {}).get("prompt_version") for m in models}
        found.add(self.manifest.get("pipeline", {}).get("prompt_version"))  # run.json before per-model settings
        return ", ".join(sorted(v for v in found if v)) or None

    @property
    def paired_metrics(self) -> list[str]:
        """The metrics scoring compared pairwise, in its order (scores meta; else as the paired rows name them)."""
        listed = self.meta.get("stats", {}).get("metrics")
        return list(listed) if listed else list(dict.fromkeys(r["metric"] for r in self.paired))

    def model_identity(self, model: str) -> dict:
        for m in self.manifest.get("models", []):
            if isinstance(m, dict) and model in (m.get("slug"), m.get("name")):
                return m
        return {}


def scores_present(run_dir: str | Path) -> bool:
    d = Path(run_dir) / SCORES_DIR
    return all((d / f"{name}.json").is_file() for name in SCORE_FILES)


def _read_json(path: Path, kind: type):
    missing = f"{path}: missing; score the run first (`vlmproprio score {path.parent.parent}`)"
    try:
        data = load_required_json(path, missing, error=ReportError)
    except (OSError, ValueError) as exc:
        raise ReportError(
            f"{path}: cannot read ({exc}); re-score the run (`vlmproprio score {path.parent.parent}`)"
        ) from exc
    if not isinstance(data, kind):
        raise ReportError(
            f"{path}: expected a JSON {kind.__name__}; re-score the run (`vlmproprio score {path.parent.parent}`)"
        )
    return data


def _check_generation(run_dir: Path, d: Path, fixtures: str | Path | None) -> None:
    if (d / "meta.json").is_file():  # else the missing-file error below says to score the run
        from vlmproprio.run_folder import ScoreRunError, check_scores

        # one generation, stamped with what it was computed from: refuse stale or mixed scores. Every file of it
        # (judge.json and frames.csv too, which sit beside the tables read here), and no file from elsewhere.
        try:
            check_scores(run_dir, fixtures=fixtures)
        except ScoreRunError as exc:  # stale scores, or a --fixtures folder that is not there
            raise ReportError(str(exc)) from None


def _check_rows(run_dir: Path, d: Path, rows: list) -> None:
    """Every row names its cell, and the cells are exactly the run's transcripts."""
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not all(k in r for k in ("model", "episode_id", "task", "condition")):
            raise ReportError(f"{d / 'rows.json'}: row {i} lacks model/episode_id/task/condition; re-score the run")
    scored = {cell_key(r["model"], r["episode_id"], r["condition"]) for r in rows}
    on_disk = {f"{p.parent.name}/{p.stem}" for p in (run_dir / "transcripts").glob("*/*.json")}
    if on_disk and on_disk != scored:
        new, gone = sorted(on_disk - scored), sorted(scored - on_disk)
        what = f"{len(new)} transcript(s) not scored (e.g. {new[0]})" if new else f"{len(gone)} scored but gone"
        raise ReportError(f"{d}: scores are out of date: {what}; re-score with `vlmproprio score {run_dir}`")


def load_run_scores(run_dir: str | Path, fixtures: str | Path | None = None) -> RunScores:
    """Read RUN_DIR/run.json (optional) and RUN_DIR/scores/*.json; checks they describe the same transcripts,
    and the ground truth in ``fixtures`` (default: run.json's fixture folder, when it is there)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ReportError(f"{run_dir}: run directory not found")
    d = run_dir / SCORES_DIR
    _check_generation(run_dir, d, fixtures)
    kinds = {"audit": dict, "traces": dict, "meta": dict, "verdicts": dict}
    # the score files are RunScores' fields of the same names
    tables = {name: _read_json(d / f"{name}.json", kinds.get(name, list)) for name in SCORE_FILES}
    manifest = _read_json(run_dir / "run.json", dict) if (run_dir / "run.json").is_file() else {}
    rows, meta = tables["rows"], tables["meta"]
    _check_rows(run_dir, d, rows)
    models = [m for m in meta.get("models", []) if isinstance(m, str)] or sorted({r["model"] for r in rows})
    conditions = [c for c in meta.get("conditions", []) if isinstance(c, str)]
    episodes = [e for e in meta.get("episodes", []) if isinstance(e, str)]
    return RunScores(
        run_dir=run_dir,
        manifest=manifest,
        **tables,
        models=models,
        conditions=conditions or list(dict.fromkeys(r["condition"] for r in rows)),
        episodes=episodes or list(dict.fromkeys(r["episode_id"] for r in rows)),
        judge=_read_json(d / "judge.json", dict) if (d / "judge.json").is_file() else None,
    )
