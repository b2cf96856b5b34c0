"""The suite from Python: ``vlmproprio.evaluate(model=..., episodes=..., conditions=..., out=...)``.

It does what the run command then the score command do, through the same runner and scorer, so its
numbers are the command line's. ``model`` is a model name (``qwen2-vl``, ``hf:/path``, ``openai:gpt-4o``,
``py:package.module:factory``) or a model object: a :class:`~vlmproprio.backends.base.Backend` or any callable
``ChatRequest -> str`` (vlmproprio.backends.python), named by ``name`` and ``revision`` for the cache key.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.backends.python import register_python_model
from vlmproprio.conditions import parse_conditions
from vlmproprio.errors import UsageError
from vlmproprio.evaluation import score_run
from vlmproprio.locations import resolve_fixtures
from vlmproprio.models import ModelRef, resolve_model
from vlmproprio.options import DEFAULT_CONDITIONS
from vlmproprio.pipeline import PipelineSettings
from vlmproprio.runner import ModelRun, RunPlan, run
from vlmproprio.sidecars import embed_recorded


@dataclass(frozen=True)
class Evaluation:
    """A scored run of one model: where it is, its score rows, verdicts and warnings, its cassette if recorded."""

    run_dir: Path
    model: ModelRef
    mode: str
    rows: list[dict]
    paired: list[dict]
    verdicts: list[dict]
    warnings: list[dict]
    cassette: Path | None

    def verdict_lines(self) -> list[str]:
        from vlmproprio.verdicts import format_verdict

        return [f"warning: {w['message']}" for w in self.warnings] + [format_verdict(v) for v in self.verdicts]


def _model_ref(model: object, name: str | None, revision: str) -> ModelRef:
    if isinstance(model, str | ModelRef):
        if name is not None:
            raise UsageError("evaluate: name= is for a model object; a model given by name is named already")
        return resolve_model(model)
    if not name:
        raise UsageError("evaluate: a model object needs name= (and revision=): they are its identity in the cache key")
    return register_python_model(name, model, revision=revision)


def evaluate(
    model: object,
    episodes: Sequence[str] | None = None,
    conditions: str | Sequence[str] = DEFAULT_CONDITIONS,
    out: str | Path = Path("runs") / "evaluate",
    *,
    name: str | None = None,
    revision: str = "",
    fixtures: str | Path | None = None,
    mode: str = "auto",
    cache_dir: str | Path | None = None,
    pipeline: PipelineSettings | None = None,
    progress: bool = True,
) -> Evaluation:
    """Caption ``episodes`` (default: all) under ``conditions`` with ``model``, write the run to ``out`` and score it.

    ``mode``: ``auto`` (the model's cassette if there is one, else the model), ``live`` (the model, through the
    response cache), ``record`` (live, and the answers written to ``<fixtures>/responses/<slug>.jsonl`` with
    their caption embeddings, so anyone can replay and re-score them without the model), ``replay``."""
    ref = _model_ref(model, name, revision)
    fixtures = resolve_fixtures(fixtures)
    plan = RunPlan(
        models=(ref,),
        conditions=tuple(parse_conditions(conditions)),
        fixtures=fixtures,
        out=Path(out),
        episode_ids=tuple(episodes) if episodes is not None else None,
        mode=mode,
        cache_dir=Path(cache_dir) if cache_dir is not None else None,
        pipeline=pipeline or PipelineSettings(),
        progress=progress,
    )
    [model_run] = run(plan)
    _embed_if_recorded(model_run, plan)
    embeddings = Path(cache_dir) / "embeddings" if cache_dir is not None else None
    tables = score_run(plan.out, fixtures=fixtures, embedding_cache=embeddings, progress=progress)
    return Evaluation(
        run_dir=plan.out,
        model=ref,
        mode=model_run.mode,
        rows=[r for r in tables.rows if r["model"] == ref.slug],
        paired=[r for r in tables.paired if r["model"] == ref.slug],
        verdicts=[v for v in tables.verdicts.get("verdicts", []) if v["model"] == ref.slug],
        warnings=[w for w in tables.verdicts.get("warnings", []) if w["model"] == ref.slug],
        cassette=Path(model_run.cassette) if model_run.cassette else None,
    )


def _embed_if_recorded(model_run: ModelRun, plan: RunPlan) -> None:
    """A recorded cassette gets its captions' embeddings beside it, as a run in record mode gives it."""
    for _name, _build in embed_recorded([model_run], plan.out, plan.fixtures):
        pass
