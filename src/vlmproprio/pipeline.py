"""The paper's captioning method (Sec. III-A) over episodes and conditions.

For one episode under one condition, with groups of k consecutive sampled frames:

* Process 1: one request per group with its k images and states -> one caption per frame;
* Process 2: one request per group with the group's frame captions, images and states -> a scene caption;
* Process 3: one request with all scene captions, the images (optionally capped) and every frame's state
  -> the final instruction.

So an episode of N sampled frames costs 2 * ceil(N / k) + 1 model calls per condition.

All (episode, condition) cells advance together in three waves (every Process 1 request, then every
Process 2, then every Process 3), so a batching backend sees large batches, and a run that is stopped and
started again finds every answer it already had in the cache. A wave goes to the answerer in chunks of
several batches (``answer_chunk``), so a backend that groups alike shapes (a local model) can pick them
across groups, episodes and conditions, while the progress bar still moves.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from vlmproprio import parsing, prompts
from vlmproprio.chat import Answer, ChatRequest, GenerationConfig, ImagePart, RequestTag, answer_problem
from vlmproprio.conditions import Condition, FrameStates, frame_states
from vlmproprio.episodes import Episode, frame_images
from vlmproprio.errors import UsageError
from vlmproprio.transcripts import FrameCaption, RequestRecord, SceneCaption, Transcript

Answerer = Callable[[Sequence[ChatRequest]], list[Answer]]
MISSING_CAPTION = "(no caption)"


@dataclass(frozen=True)
class PipelineSettings:
    k: int = 5  # frames per group (the paper's k)
    frame_stride: int = 1  # use every n-th sampled frame; 1 = the fixtures' every-20-sim-steps sampling
    max_images_p3: int | None = None  # cap on images in Process 3, evenly spaced; None = all frames
    prompt: prompts.PromptOptions = field(default_factory=prompts.PromptOptions)
    generation: GenerationConfig = field(default_factory=GenerationConfig)

    def __post_init__(self) -> None:
        if self.k < 1:
            raise UsageError(f"k must be at least 1, got {self.k}")
        if self.frame_stride < 1:
            raise UsageError(f"frame stride must be at least 1, got {self.frame_stride}")
        if self.max_images_p3 is not None and self.max_images_p3 < 0:
            raise UsageError(f"max images for Process 3 must be >= 0, got {self.max_images_p3}")

    def to_dict(self) -> dict:
        return {
            "k": self.k,
            "frame_stride": self.frame_stride,
            "max_images_p3": self.max_images_p3,
            "prompt_example": self.prompt.example,
            "prompt_version": prompts.prompt_version(self.prompt),
            "generation": self.generation.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> PipelineSettings:
        """The settings ``to_dict`` recorded (run.json models[].pipeline), the prompt version included."""
        recorded = str(d.get("prompt_version", ""))
        version = "paper-verbatim" if recorded.startswith("paper-verbatim") else "suite"
        return cls(
            k=int(d["k"]),
            frame_stride=int(d["frame_stride"]),
            max_images_p3=d.get("max_images_p3"),
            prompt=prompts.PromptOptions(example=bool(d.get("prompt_example", True)), version=version),
            generation=GenerationConfig(**d.get("generation", {})),
        )


def groups(n: int, k: int) -> list[range]:
    """Consecutive groups of k frame positions; the last one may be shorter."""
    return [range(i, min(i + k, n)) for i in range(0, n, k)]


def calls_per_episode(n_frames: int, k: int) -> int:
    return 2 * len(groups(n_frames, k)) + 1


def capped_positions(n: int, cap: int | None) -> list[int]:
    if cap is None or cap >= n:
        return list(range(n))
    if cap == 0:
        return []
    return sorted({int(i) for i in np.rint(np.linspace(0, n - 1, cap))})


class CellRun:
    """One (episode, condition): builds its requests stage by stage and collects the parsed answers."""

    def __init__(
        self,
        episode: Episode,
        condition: Condition,
        images: Sequence[ImagePart],
        states: FrameStates,
        settings: PipelineSettings,
    ):
        self.episode, self.condition, self.settings = episode, condition, settings
        self.positions = list(range(0, len(episode.frames), settings.frame_stride))
        self.images = images
        self.states = states
        self.groups = groups(len(self.positions), settings.k)
        self.frame_captions: list[parsing.Parsed] = []
        self.scene_captions: list[parsing.Parsed] = []
        self.final: parsing.Parsed | None = None
        self.records: list[RequestRecord] = []
        self._views: dict[tuple[int, int], prompts.FrameView] = {}

    # views -----------------------------------------------------------------------------------
    def _view(self, pos: int, number: int) -> prompts.FrameView:
        # Processes 1 and 2 show the same views, Process 3 most of them again: format each state line once
        view = self._views.get((pos, number))
        if view is None:
            view = self._views[(pos, number)] = self._new_view(pos, number)
        return view

    def _new_view(self, pos: int, number: int) -> prompts.FrameView:
        i = self.positions[pos]
        s = self.states
        words = s.words[i] if s.words is not None else None
        joints = s.joints[i] if s.joints is not None else None
        ee = s.ee[i] if s.ee is not None else None
        return prompts.FrameView(
            number=number,
            image=self.images[i] if self.condition.images else None,
            state=prompts.state_text(number, self.condition, joints, ee, words),
        )

    def _request(self, messages, stage: str, group: int) -> ChatRequest:
        return ChatRequest(
            messages=messages,
            config=self.settings.generation,
            prompt_version=prompts.prompt_version(self.settings.prompt),
            tag=RequestTag(self.episode.episode_id, self.condition.name, stage, group),
        )

    def _record(self, stage: str, group: int, answer: Answer, reasoning: str) -> None:
        extra = answer.meta.extra if isinstance(answer.meta.extra, dict) else {}
        self.records.append(
            RequestRecord(
                stage,
                group,
                answer.key,
                answer.from_cache,
                answer.meta.latency_s,
                "\n\n".join(r for r in (answer.reasoning, reasoning) if r),  # the server's field, then the text's
                finish_reason=_reported(extra, "finish_reason"),
                response_model=_reported(extra, "response_model"),
                problem=answer_problem(answer.meta),
            )
        )

    # stages ----------------------------------------------------------------------------------
    def p1_requests(self) -> list[ChatRequest]:
        out = []
        for g, members in enumerate(self.groups):
            views = [self._view(pos, j + 1) for j, pos in enumerate(members)]
            out.append(self._request(prompts.process1(views, self.condition, self.settings.prompt), "p1", g))
        return out

    def accept_p1(self, answers: Sequence[Answer]) -> None:
        for g, (members, answer) in enumerate(zip(self.groups, answers, strict=True)):
            read = parsing.parse_frame_answer(answer.text, len(members), offset=members.start)
            self._record("p1", g, answer, read.reasoning)
            self.frame_captions += read.captions

    def p2_requests(self) -> list[ChatRequest]:
        out = []
        for g, members in enumerate(self.groups):
            views = [self._view(pos, j + 1) for j, pos in enumerate(members)]
            caps = [self.frame_captions[pos].text or MISSING_CAPTION for pos in members]
            msgs = prompts.process2(views, caps, self.condition, self.settings.prompt)
            out.append(self._request(msgs, "p2", g))
        return out

    def accept_p2(self, answers: Sequence[Answer]) -> None:
        for g, answer in enumerate(answers):
            read = parsing.parse_single_answer(answer.text)
            self._record("p2", g, answer, read.reasoning)
            self.scene_captions.append(read.caption)

    def p3_request(self) -> ChatRequest:
        with_image = set(capped_positions(len(self.positions), self.settings.max_images_p3))
        views = []
        for pos in range(len(self.positions)):
            v = self._view(pos, pos + 1)
            views.append(v if pos in with_image else prompts.FrameView(v.number, None, v.state))
        scenes = [s.text or MISSING_CAPTION for s in self.scene_captions]
        return self._request(prompts.process3(views, scenes, self.condition, self.settings.prompt), "p3", -1)

    def accept_p3(self, answer: Answer) -> None:
        read = parsing.parse_single_answer(answer.text)
        self._record("p3", -1, answer, read.reasoning)
        self.final = read.caption

    def timing(self) -> dict[str, float]:
        """Model time per stage for this cell (latencies as the backend reported them; 0 for cache hits)."""
        out = {f"{stage}_s": 0.0 for stage in ("p1", "p2", "p3")}
        for r in self.records:
            out[f"{r.stage}_s"] += 0.0 if r.from_cache else r.latency_s
        return {k: round(v, 4) for k, v in out.items()}

    def transcript(self, model: str) -> Transcript:
        frames = [
            FrameCaption(pos, self.episode.frames[self.positions[pos]].step, p.text, p.status, *_audit(p))
            for pos, p in enumerate(self.frame_captions)
        ]
        scenes = [
            SceneCaption(g, tuple(members), p.text, p.status, *_audit(p))
            for g, (members, p) in enumerate(zip(self.groups, self.scene_captions, strict=True))
        ]
        assert self.final is not None
        final_span, final_removed = _audit(self.final)
        return Transcript(
            model=model,
            episode_id=self.episode.episode_id,
            task=self.episode.task,
            condition=self.condition.name,
            prompt_version=prompts.prompt_version(self.settings.prompt),
            frames=frames,
            scenes=scenes,
            final=self.final.text,
            final_status=self.final.status,
            requests=list(self.records),
            timing=self.timing(),
            final_span=final_span,
            final_removed=final_removed,
        )


def _reported(extra: dict, name: str) -> str:
    value = extra.get(name, "")
    return value if isinstance(value, str) else ""


def _audit(p: parsing.Parsed) -> tuple[str, tuple[str, ...]]:
    """What a transcript keeps of a caption's audit: nothing for an exact caption (its span is the caption's own
    line, and a clean answer's transcript must not change), else the raw span and the classes removed."""
    return ("", ()) if p.status == "ok" else (p.span, p.removed)


DEFAULT_CHUNK = 64
CHUNK_BATCHES = 8  # batches per answerer call


def answer_chunk(max_batch_size: int) -> int:
    """Requests per answerer call for a backend taking ``max_batch_size`` per batch: ``CHUNK_BATCHES`` batches
    to group by shape (one model's Process 1 wave is about 1,100 requests), at least ``DEFAULT_CHUNK``."""
    return max(DEFAULT_CHUNK, CHUNK_BATCHES * max(1, int(max_batch_size)))


def _answer_in_chunks(requests: list[ChatRequest], answer: Answerer, chunk: int, bar) -> list[Answer]:
    out: list[Answer] = []
    for i in range(0, len(requests), chunk):
        part = requests[i : i + chunk]
        got = answer(part)
        if len(got) != len(part):
            raise RuntimeError(f"backend returned {len(got)} answers for {len(part)} requests")
        out += got
        if bar is not None:
            bar.update(len(part))
    return out


def episode_images(episodes: Sequence[Episode]) -> dict[str, list[ImagePart]]:
    """Every frame's image, by episode id: read and pixel-checked once, shared by every condition."""
    frames = frame_images([f for ep in episodes for f in ep.frames])
    out, start = {}, 0
    for ep in episodes:
        out[ep.episode_id] = [ImagePart(data) for data in frames[start : start + len(ep.frames)]]
        start += len(ep.frames)
    return out


def caption_episodes(
    episodes: Sequence[Episode],
    conditions: Sequence[Condition],
    answer: Answerer,
    model: str,
    settings: PipelineSettings = PipelineSettings(),
    *,
    peers: Sequence[Episode] | None = None,
    chunk: int = DEFAULT_CHUNK,
    progress: bool = True,
    images: Mapping[str, Sequence[ImagePart]] | None = None,
    bar_label: str = "",
) -> list[Transcript]:
    """Run Processes 1-3 for every (episode, condition); one Transcript each, in episode-major order.

    ``peers`` are the episodes the ``both_shuffled`` control may borrow states from (default: ``episodes``);
    ``images``: ``episode_images`` of at least ``episodes``, when the caller has read them already; ``bar_label``
    is added to the progress bar's name (which block of a larger set this is)."""
    from tqdm import tqdm

    peers = episodes if peers is None else peers
    images = episode_images(episodes) if images is None else images
    runs: list[CellRun] = []
    for ep in episodes:
        for cond in conditions:
            runs.append(CellRun(ep, cond, images[ep.episode_id], frame_states(ep, cond, peers), settings))
    total = sum(2 * len(r.groups) + 1 for r in runs)
    # no bar at all without progress, not a disabled one: tqdm takes its class lock even then, and a forked
    # worker (vlmproprio.runner) could inherit that lock held by the parent's tqdm monitor thread
    bar_or_none = tqdm(total=total, desc=f"captioning ({model}{bar_label})", unit="req") if progress else nullcontext()
    with bar_or_none as bar:
        answers = iter(_answer_in_chunks([q for r in runs for q in r.p1_requests()], answer, chunk, bar))
        for r in runs:
            r.accept_p1([next(answers) for _ in r.groups])
        answers = iter(_answer_in_chunks([q for r in runs for q in r.p2_requests()], answer, chunk, bar))
        for r in runs:
            r.accept_p2([next(answers) for _ in r.groups])
        finals = _answer_in_chunks([r.p3_request() for r in runs], answer, chunk, bar)
        for r, a in zip(runs, finals, strict=True):
            r.accept_p3(a)
    return [r.transcript(model) for r in runs]
