"""The paper's method as an inspect_ai task, scored by the suite's own rubric and segmentation.

::

    inspect eval vlmproprio/proprio_captions -T condition=both --model openai/gpt-4o
    inspect eval vlmproprio/proprio_captions -T condition=none,both -T episodes=door_00,bin2_01 \\
        --model vlmproprio/reference          # the suite's rule-based captioner, offline
    inspect view                              # the logs: every request, answer and score

inspect_ai finds this module through the ``inspect_ai`` entry point in pyproject.toml. What it holds:

* ``proprio_captions``: the task; one sample per (episode, condition) of a fixture set (the shipped 22
  episodes, or any imported set: ``-T fixtures=PATH``).
* ``paper_processes``: the solver. It builds the requests with vlmproprio's own pipeline (``CellRun``: the
  paper's Process 1 per group of k frames, Process 2 per group, Process 3 once, prompts rendered from
  ``vlmproprio.prompts``) and parses the answers with ``vlmproprio.parsing``; only the model calls go through
  inspect's model API (so inspect's providers, retries, concurrency limits, caching and logs apply). The
  sample's Transcript is kept in its store (``vlmproprio.transcript``).
* ``caption_rubric`` and ``segmentation``: the scorers. Both hand the transcript to
  ``vlmproprio.evaluation.score_run`` -- the very function ``vlmproprio score RUN_DIR`` runs -- and report its row:
  nothing here scores captions its own way, so a score in an inspect log equals the suite's for the same
  answers.
* ``vlmproprio/<model>``: a model provider for inspect that answers with a vlmproprio backend
  (``vlmproprio/reference``, the rule-based captioner; ``vlmproprio/tiny-qwen2-vl``; ``vlmproprio/hf:PATH``).

Needs ``pip install 'vlmproprio[inspect]'`` (inspect_ai and the sentence encoder the segmentation uses).
"""

from __future__ import annotations

import atexit
import base64
import binascii
import functools
import hashlib
import json
import math
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import anyio
import anyio.to_thread
from inspect_ai import Task, task
from inspect_ai.dataset import MemoryDataset, Sample
from inspect_ai.model import (
    ChatMessage,
    ChatMessageAssistant,
    ChatMessageSystem,
    ChatMessageUser,
    ContentImage,
    ContentText,
    GenerateConfig,
    ModelAPI,
    ModelOutput,
    get_model,
    modelapi,
)
from inspect_ai.scorer import Metric, SampleScore, Score, Target, grouped, mean, metric, scorer
from inspect_ai.solver import Generate, TaskState, solver
from inspect_ai.util import collect, span

from vlmproprio import prompts
from vlmproprio.cache import request_key
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, GenerationConfig, ImagePart, Message, TextPart
from vlmproprio.conditions import frame_states, get_condition, parse_conditions
from vlmproprio.episodes import Episode, frame_images, load_episodes
from vlmproprio.errors import UsageError, VlmproprioError
from vlmproprio.evaluation import score_run
from vlmproprio.evaluation.metrics import caption_metrics, segmentation_paired
from vlmproprio.locations import resolve_fixtures
from vlmproprio.pipeline import CellRun, PipelineSettings
from vlmproprio.segmentation import DEFAULT_THRESHOLD, caption_present
from vlmproprio.transcripts import Transcript, cell_key, cell_name, write_transcript

DEFAULT_FIXTURES = ""  # "": --fixtures rules of the CLI ($VLMPROPRIO_FIXTURES, else the repository's)
TRANSCRIPT_KEY = "vlmproprio.transcript"
# The metrics the scores pair between conditions (the metric table's paired ones), split by what they measure.
RUBRIC_METRICS = caption_metrics()
# at the fixed threshold: one sample cannot choose a threshold on the other episodes (the leave-one-episode-out
# scores of `vlmproprio score RUN_DIR` need the whole run), so the out-of-sample columns become their fixed-threshold twins
SEGMENTATION_METRICS = tuple(m.replace("seg_loo_", "seg_") for m in segmentation_paired())
IMAGE_DATA_PREFIX = "data:"
RUN_MODEL = "inspect"  # the model's folder name in the one-transcript run the scorers hand to score_run


# ---------------------------------------------------------------------------------------------- fixtures


@functools.cache
def _fixture_set(root: str) -> dict[str, Episode]:
    """Every episode of a fixture set, verified once per process (both_shuffled borrows from any of them)."""
    if not Path(root).is_dir():
        raise UsageError(f"fixture folder {root} not found; pass -T fixtures=PATH (a folder with a manifest.json)")
    return {ep.episode_id: ep for ep in load_episodes(Path(root))}


def _root(fixtures: str) -> str:
    """The fixture folder as the CLI finds it (vlmproprio.locations), never just the current folder's."""
    return str(resolve_fixtures(fixtures or None).resolve())


def _id_list(value: str | Sequence[str] | None) -> list[str] | None:
    if value is None:
        return None
    items = value.split(",") if isinstance(value, str) else list(value)
    return [s.strip() for s in items if s.strip()] or None


# ---------------------------------------------------------------------------------------------- messages


def _data_uri(image: ImagePart) -> str:
    return f"data:{image.mime};base64,{base64.b64encode(image.data).decode('ascii')}"


def to_inspect_messages(request: ChatRequest) -> list[ChatMessage]:
    """A vlmproprio request as inspect chat messages: the same text parts and image bytes, in order."""
    kinds = {"system": ChatMessageSystem, "user": ChatMessageUser, "assistant": ChatMessageAssistant}
    out: list[ChatMessage] = []
    for m in request.messages:
        content: list[Any] = [
            ContentText(text=p.text) if isinstance(p, TextPart) else ContentImage(image=_data_uri(p)) for p in m.parts
        ]
        out.append(kinds[m.role](content=content))
    return out


def _image_part(uri: str) -> ImagePart:
    head, sep, data = uri.partition(",")
    if not (uri.startswith(IMAGE_DATA_PREFIX) and sep and head.endswith(";base64")):
        raise UsageError(f"vlmproprio models take images as base64 data URIs, got {uri[:40]!r}")
    try:
        return ImagePart(base64.b64decode(data, validate=True), mime=head[len(IMAGE_DATA_PREFIX) : -len(";base64")])
    except (binascii.Error, ValueError) as exc:
        raise UsageError(f"an image data URI is not valid base64 ({exc})") from exc


def from_inspect_messages(messages: Sequence[ChatMessage], config: GenerationConfig) -> ChatRequest:
    """inspect chat messages as a vlmproprio request (the inverse of ``to_inspect_messages``)."""
    out = []
    for m in messages:
        if m.role not in ("system", "user", "assistant"):
            raise UsageError(f"vlmproprio models answer chat messages, not {m.role!r} messages")
        items = [ContentText(text=m.content)] if isinstance(m.content, str) else m.content
        parts: list[TextPart | ImagePart] = []
        for c in items:
            if isinstance(c, ContentText):
                parts.append(TextPart(c.text))
            elif isinstance(c, ContentImage):
                parts.append(_image_part(c.image))
            else:
                raise UsageError(f"vlmproprio models take text and images, not {c.type!r} content")
        out.append(Message(m.role, tuple(parts)))
    return ChatRequest(messages=tuple(out), config=config)


def inspect_config(g: GenerationConfig) -> GenerateConfig:
    """The suite's decoding settings (the paper's: greedy) as an inspect GenerateConfig."""
    return GenerateConfig(max_tokens=g.max_new_tokens, temperature=g.temperature, seed=g.seed)


# ---------------------------------------------------------------------------------------------- solver


async def _answer(model, requests: Sequence[ChatRequest]) -> list[tuple[Answer, ModelOutput]]:
    """Ask inspect's model every request (concurrently: inspect limits connections); answers in order.

    ``collect`` rather than asyncio.gather: it works under either of inspect's async backends (asyncio, trio)
    and groups each call's events in the log."""
    identity = {"backend": "inspect", "model_id": str(model)}

    async def one(req: ChatRequest) -> tuple[Answer, ModelOutput]:
        t0 = time.perf_counter()
        out = await model.generate(to_inspect_messages(req), config=inspect_config(req.config))
        meta = AnswerMeta(
            backend="inspect",
            model_id=str(model),
            prompt_tokens=out.usage.input_tokens if out.usage else 0,
            completion_tokens=out.usage.output_tokens if out.usage else 0,
            latency_s=time.perf_counter() - t0,
        )
        return Answer(out.completion, meta, key=request_key(identity, req)), out

    return await collect(*(one(r) for r in requests))


def pipeline_settings(
    k: int = 5, frame_stride: int = 1, max_images_p3: int | None = None, example: bool = True, max_tokens: int = 512
) -> PipelineSettings:
    return PipelineSettings(
        k=int(k),
        frame_stride=int(frame_stride),
        max_images_p3=None if max_images_p3 is None else int(max_images_p3),
        prompt=prompts.PromptOptions(example=bool(example)),
        generation=GenerationConfig(max_new_tokens=int(max_tokens)),
    )


@solver
def paper_processes(fixtures: str = DEFAULT_FIXTURES, **pipeline: Any):
    """Processes 1-3 of the paper for the sample's (episode, condition), with vlmproprio's prompts and parser.

    ``pipeline``: the settings ``pipeline_settings`` takes (k, frame_stride, max_images_p3, example, max_tokens;
    the defaults are its own), so the solver and the task cannot disagree on them."""
    settings = pipeline_settings(**pipeline)

    async def solve(state: TaskState, generate: Generate) -> TaskState:
        episodes = _fixture_set(str(Path(state.metadata.get("fixtures", fixtures)).resolve()))
        ep = episodes[state.metadata["episode_id"]]
        cond = get_condition(state.metadata["condition"])
        images = [ImagePart(data) for data in frame_images(ep.frames)]
        cell = CellRun(ep, cond, images, frame_states(ep, cond, list(episodes.values())), settings)
        model = get_model()
        async with span("process 1: a caption per frame"):
            cell.accept_p1([a for a, _ in await _answer(model, cell.p1_requests())])
        async with span("process 2: a caption per scene"):
            cell.accept_p2([a for a, _ in await _answer(model, cell.p2_requests())])
        p3 = cell.p3_request()
        async with span("process 3: the instruction"):
            [(final, output)] = await _answer(model, [p3])
        cell.accept_p3(final)
        transcript = cell.transcript(str(model))
        state.store.set(TRANSCRIPT_KEY, transcript.to_dict())
        # the sample's conversation in the log: the Process 3 request and its answer (every call is an event)
        state.messages = [*to_inspect_messages(p3), ChatMessageAssistant(content=final.text)]
        state.output = output
        return state

    return solve


# ---------------------------------------------------------------------------------------------- scorers


def _fixture_sidecars(fixtures: str) -> list[Path]:
    """Every caption-embedding sidecar beside the fixtures' cassettes. A vector is keyed by encoder and text, so
    any model's sidecar serves any transcript: a caption the suite scored from a sidecar gets the very same bits
    here, whichever machine (and float order) this runs on."""
    from vlmproprio.embeddings import SIDECAR_SUFFIX

    return sorted((Path(fixtures) / "responses").glob("*" + SIDECAR_SUFFIX))


@functools.cache
def _embedder(embedding_cache: str | None, fixtures: str):
    """One sentence encoder per process. score_run opens its own embedder, which would load the encoder again
    for every sample; embedding a transcript's captions here first leaves it only cached vectors to read, and a
    text's vector does not depend on what is embedded with it (vlmproprio.embeddings), so the scores are the same."""
    from vlmproprio.embeddings import (
        CachedEmbedder,
        EmbeddingStore,
        default_embedding_dir,
        encoder_spec,
        read_sidecar,
        sidecar_vectors,
    )

    directory = Path(embedding_cache) if embedding_cache else default_embedding_dir()
    store = EmbeddingStore(directory)
    atexit.register(store.close)
    spec = encoder_spec(memo_dir=directory)
    stored = sidecar_vectors([read_sidecar(p) for p in _fixture_sidecars(fixtures)], spec.key)
    return CachedEmbedder(spec, store, sidecar=stored)


@functools.cache
def _suite_row_cached(transcript_json: str, fixtures: str, threshold: float, embedding_cache: str | None) -> dict:
    transcript = Transcript.from_dict(json.loads(transcript_json))
    # a run folder names models by folder; inspect's names have slashes ("openai/gpt-4o"), and no score uses it
    transcript.model = RUN_MODEL
    _embedder(embedding_cache, fixtures).embed([f.text for f in transcript.frames if caption_present(f.text, f.status)])
    with tempfile.TemporaryDirectory(prefix="vlmproprio-inspect-") as tmp:
        run_dir = Path(tmp)
        write_transcript(run_dir, transcript)
        tables = score_run(
            run_dir,
            fixtures=fixtures,
            embedding_cache=embedding_cache,
            sidecars=_fixture_sidecars(fixtures),
            threshold=threshold,
            comparisons=[],
            write=False,
        )
    key = cell_key(transcript.model, transcript.episode_id, transcript.condition)
    [row] = tables.rows
    return {"row": row, "audit": tables.audit[key], "trace": tables.traces[key]}


def suite_scores(
    transcript: dict, fixtures: str, threshold: float = DEFAULT_THRESHOLD, embedding_cache: str | None = None
) -> dict:
    """vlmproprio's scores of one transcript: ``score_run`` over a one-transcript run (memoised per process, so
    the two scorers share one computation)."""
    doc = json.dumps(transcript, sort_keys=True, ensure_ascii=False)
    return _suite_row_cached(doc, _root(fixtures), float(threshold), embedding_cache)


def _number(v) -> float:
    return float("nan") if v is None else float(v)


def _scores_of(state: TaskState, fixtures: str, threshold: float, embedding_cache: str | None) -> dict:
    transcript = state.store.get(TRANSCRIPT_KEY)
    if transcript is None:
        raise VlmproprioError(f"sample {state.sample_id}: no transcript in its store (use the paper_processes solver)")
    return suite_scores(transcript, state.metadata.get("fixtures", fixtures), threshold, embedding_cache)


@metric(name="both-none")
def both_minus_none() -> Metric:
    """The paired difference the suite exists for: per episode, its score under ``both`` minus under ``none``,
    averaged over the episodes run under both conditions (NaN when none was). A pooled mean over all conditions
    would hide it."""

    def compute(scores: list[SampleScore]) -> float:
        cells: dict[str, dict[str, float]] = {}
        for s in scores:
            meta = s.sample_metadata or {}
            cells.setdefault(meta.get("episode_id"), {})[meta.get("condition")] = s.score.as_float()
        diffs = [c["both"] - c["none"] for c in cells.values() if "both" in c and "none" in c]
        diffs = [d for d in diffs if math.isfinite(d)]
        return float(sum(diffs) / len(diffs)) if diffs else float("nan")

    return compute


def _metrics_by_condition() -> list[Metric]:
    """The headline first (both − none, paired), then each condition's mean (inspect names them
    ``grouped_mean[<condition>]``)."""
    return [both_minus_none(), grouped(mean(), "condition", all=False, name_template="mean[{group_name}]")]


@scorer(metrics={m: _metrics_by_condition() for m in RUBRIC_METRICS})
def caption_rubric(
    fixtures: str = DEFAULT_FIXTURES, threshold: float = DEFAULT_THRESHOLD, embedding_cache: str | None = None
):
    """The final instruction under vlmproprio's rubric: object, action, trajectory mentioned and correct."""

    async def score(state: TaskState, target: Target) -> Score:
        s = _scores_of(state, fixtures, threshold, embedding_cache)
        row, final = s["row"], s["audit"]["final"]
        matched = "; ".join(f"{m['item']} {m['verdict']}: {m['text']!r}" for m in final["matches"]) or "no rubric word"
        return Score(
            value={m: _number(row[m]) for m in RUBRIC_METRICS},
            answer=final["text"],
            explanation=f"{matched} (expected: {target.text})",
            metadata={"row": row, "final": final, "expectation": s["audit"]["expectation"]},
        )

    return score


@scorer(metrics={m: _metrics_by_condition() for m in SEGMENTATION_METRICS})
def segmentation(
    fixtures: str = DEFAULT_FIXTURES, threshold: float = DEFAULT_THRESHOLD, embedding_cache: str | None = None
):
    """Segmentation points from the frame captions' embedding similarity, against the ground-truth phases."""

    async def score(state: TaskState, target: Target) -> Score:
        s = _scores_of(state, fixtures, threshold, embedding_cache)
        row, trace = s["row"], s["trace"]
        return Score(
            value={m: _number(row[m]) for m in SEGMENTATION_METRICS},
            answer=f"boundaries after frames {trace['predicted_boundaries']}",
            explanation=f"true boundaries after frames {trace['true_boundaries']} (threshold {threshold})",
            metadata={"trace": trace},
        )

    return score


# ---------------------------------------------------------------------------------------------- task


def samples(fixtures: str, condition: str, episodes: str | Sequence[str] | None = None) -> list[Sample]:
    """One sample per (episode, condition); the target is the episode's instruction in words (for reading)."""
    root = _root(fixtures)
    known = _fixture_set(root)
    ids = _id_list(episodes) or list(known)
    unknown = [i for i in ids if i not in known]
    if unknown:
        raise UsageError(f"unknown episode(s) {', '.join(unknown)} in {fixtures} (known: {', '.join(known)})")
    out = []
    for eid in ids:
        ep = known[eid]
        for cond in parse_conditions(condition):
            out.append(
                Sample(
                    id=cell_name(eid, cond.name),
                    input=f"Caption robot episode {eid} ({ep.task}, {len(ep.frames)} frames) under condition "
                    f"{cond.name}: {cond.description}",
                    target=ep.instruction,
                    metadata={"episode_id": eid, "task": ep.task, "condition": cond.name, "fixtures": root},
                )
            )
    return out


@task
def proprio_captions(
    condition: str = "both",
    episodes: str | None = None,
    fixtures: str = DEFAULT_FIXTURES,
    k: int = 5,
    frame_stride: int = 1,
    max_images_p3: int | None = None,
    example: bool = True,
    max_tokens: int = 512,
    threshold: float = DEFAULT_THRESHOLD,
    embedding_cache: str | None = None,
) -> Task:
    """Does proprioception help a VLM caption and segment robot episodes? (Suzuki, Shimizu & Ogata 2025)

    Args:
        condition: one or more of none, ee, joint, both, both_shuffled, both_noisy, state_only, primitives
            (comma-separated; 'paper', 'controls' and 'all' name groups).
        episodes: comma-separated episode ids (default: every episode of the fixture set).
        fixtures: a vlmproprio fixture folder (default: $VLMPROPRIO_FIXTURES, else the fixtures/ of the repository
            the command runs in, as for the CLI).
        k: frames per group (the paper's k).
        frame_stride: use every n-th sampled frame.
        max_images_p3: cap on the images in Process 3 (default: all).
        example: include the worked cube-stacking example in the prompts.
        max_tokens: new tokens per answer.
        threshold: similarity threshold for segmentation points.
        embedding_cache: folder of the sentence-embedding cache (default: vlmproprio's).
    """
    ds = MemoryDataset(samples(fixtures, condition, episodes), name="vlmproprio-episodes")
    return Task(
        dataset=ds,
        solver=paper_processes(
            fixtures,
            k=k,
            frame_stride=frame_stride,
            max_images_p3=max_images_p3,
            example=example,
            max_tokens=max_tokens,
        ),
        scorer=[
            caption_rubric(fixtures, threshold, embedding_cache),
            segmentation(fixtures, threshold, embedding_cache),
        ],
        metadata={
            "prompt_version": prompts.prompt_version(prompts.PromptOptions(example=bool(example))),
            "fixtures_manifest_sha256": _manifest_digest(fixtures),
        },
    )


def _manifest_digest(fixtures: str) -> str:
    path = Path(fixtures) / "manifest.json"
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else ""


# ---------------------------------------------------------------------------------------------- model provider


class VlmproprioModelAPI(ModelAPI):
    """inspect's door to vlmproprio's backends: ``--model vlmproprio/reference`` and other local models."""

    def __init__(
        self,
        model_name: str,
        base_url: str | None = None,
        api_key: str | None = None,
        config: GenerateConfig | None = None,
        **model_args: Any,
    ) -> None:
        super().__init__(model_name, base_url, api_key, [], config or GenerateConfig())
        from vlmproprio.backends.registry import create_backend

        self.backend = create_backend(model_name, mode="live")
        self._lock = anyio.Lock()  # a local backend answers one batch at a time

    async def generate(self, input, tools, tool_choice, config: GenerateConfig) -> ModelOutput:
        gen = GenerationConfig(
            max_new_tokens=config.max_tokens or GenerationConfig.max_new_tokens,
            temperature=config.temperature if config.temperature is not None else 0.0,
            seed=config.seed if config.seed is not None else 0,
        )
        request = from_inspect_messages(input, gen)
        async with self._lock:
            [answer] = await anyio.to_thread.run_sync(self.backend.generate, [request])
        return ModelOutput.from_content(model=self.model_name, content=answer.text)

    async def aclose(self) -> None:
        self.backend.close()


@modelapi(name="vlmproprio")
def vlmproprio_models():
    return VlmproprioModelAPI
