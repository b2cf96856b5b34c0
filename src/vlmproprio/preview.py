"""What a run will cost before it runs (``vlmproprio run --model NAME --dry-run``): requests and images per model, process
and condition, and how many answers the response cache (or the cassette) already holds.

The requests are the run's own: the pipeline builds them exactly as a run would, but nothing calls a model.
A cached answer is followed to the requests that depend on it (Process 2 reads Process 1's captions, Process 3
the scene captions); a request behind an answer the model has yet to give cannot be cached by then, and is
counted as one the model will compute. Rule-based captioners and cassette replays cost nothing and are answered.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from vlmproprio.answering import open_answerer
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.episodes import Episode, load_episodes
from vlmproprio.errors import VlmproprioError
from vlmproprio.models import ModelRef
from vlmproprio.pipeline import caption_episodes

if TYPE_CHECKING:
    from vlmproprio.answering import Answerer
    from vlmproprio.runner import RunPlan

STAGES = ("p1", "p2", "p3")
STAGE_LABELS = {"p1": "Process 1 (frames)", "p2": "Process 2 (scenes)", "p3": "Process 3 (final)"}


@dataclass
class CostRow:
    model: str
    stage: str
    condition: str
    requests: int = 0
    images: int = 0
    cached: int = 0  # answered without the model: the response cache, a cassette, rules

    @property
    def to_compute(self) -> int:
        return self.requests - self.cached


@dataclass
class ModelCost:
    model: str
    mode: str
    rows: list[CostRow]
    note: str = ""  # why the cached column is unknown, when the backend cannot even be set up here


class _Counter:
    """An answer function for the pipeline that counts and answers only from what costs nothing."""

    def __init__(self, model: str, answerer: Answerer | None) -> None:
        self.model = model
        self.answerer = answerer
        self.rows: dict[tuple[str, str], CostRow] = {}

    def __call__(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        free = self.answerer is not None and not self.answerer.backend.calls_model
        answers = self.answerer.answer(requests) if free else [self._cached(r) for r in requests]
        for request, answer in zip(requests, answers, strict=True):
            row = self.rows.setdefault(
                (request.tag.stage, request.tag.condition),
                CostRow(self.model, request.tag.stage, request.tag.condition),
            )
            row.requests += 1
            row.images += len(request.images)
            row.cached += int(free or answer.from_cache)
        return answers

    def _cached(self, request: ChatRequest) -> Answer:
        cache = self.answerer.cache if self.answerer is not None else None
        entry = cache.get(self.answerer.key(request)) if cache is not None else None
        if entry is not None and entry.status == "ok":
            return entry.to_answer(from_cache=True)
        return Answer("", AnswerMeta("dry-run", "not answered"))  # what depends on it is not cached either


def _model_cost(model: ModelRef, plan: RunPlan, episodes: list[Episode], peers: list[Episode]) -> ModelCost:
    settings = replace(plan.backend or BackendSettings(), cassette_dir=plan.fixtures / "responses")
    pipeline = plan.pipeline_for(model)
    # record mode asks the same requests as live; previewing must not write the model's cassette
    mode = "live" if plan.mode == "record" else plan.mode
    try:
        with open_answerer(model, mode, settings, plan.cache_dir) as answerer:
            if not answerer.backend.calls_model:
                answerer.cache = None  # rules and cassettes answer for free: nothing to look up, nothing to store
            counter = _Counter(model.name, answerer)
            caption_episodes(episodes, plan.conditions, counter, model.slug, pipeline, peers=peers, progress=False)
            mode, note = answerer.mode, ""
    except VlmproprioError as exc:  # no weights, no key, no cassette: the requests can still be counted
        counter = _Counter(model.name, None)
        caption_episodes(episodes, plan.conditions, counter, model.slug, pipeline, peers=peers, progress=False)
        mode, note = plan.mode, f"cached answers unknown: {exc}"
    order = {c.name: i for i, c in enumerate(plan.conditions)}
    rows = sorted(counter.rows.values(), key=lambda r: (STAGES.index(r.stage), order.get(r.condition, 99)))
    return ModelCost(model.name, mode, rows, note)


def preview_run(plan: RunPlan) -> list[ModelCost]:
    """Each model's requests, images and cached answers for ``plan``; no model is called, no answer stored."""
    peers = load_episodes(plan.fixtures)
    wanted = plan.episode_ids
    episodes = peers if wanted is None else [e for e in peers if e.episode_id in set(wanted)]
    return [_model_cost(m, plan, episodes, peers) for m in plan.models]


def format_costs(costs: Sequence[ModelCost]) -> str:
    lines = []
    for c in costs:

        def cached(n: int, c: ModelCost = c) -> str:
            return "?" if c.note else str(n)  # without a backend the cache cannot be asked

        lines.append(f"{c.model} ({c.mode} mode):")
        lines.append(
            f"  {'process':<20} {'condition':<14} {'requests':>8} {'images':>7} {'cached':>7} {'to compute':>10}"
        )
        for r in c.rows:
            lines.append(
                f"  {STAGE_LABELS[r.stage]:<20} {r.condition:<14} {r.requests:>8} {r.images:>7} "
                f"{cached(r.cached):>7} {cached(r.to_compute):>10}"
            )
        total = [sum(getattr(r, f) for r in c.rows) for f in ("requests", "images", "cached")]
        lines.append(
            f"  {'total':<35} {total[0]:>8} {total[1]:>7} {cached(total[2]):>7} {cached(total[0] - total[2]):>10}"
        )
        if c.note:
            lines.append(f"  {c.note}")
    return "\n".join(lines) + "\n"
