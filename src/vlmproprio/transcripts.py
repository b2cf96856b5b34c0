"""Transcript: everything a model said about one episode under one condition.

The pipeline writes one Transcript per (model, episode, condition) as JSON into
a run directory; scoring and segmentation read them back, so a run can be
re-scored later without the model.

A caption that was not given in the exact requested form carries its audit: ``span``, the raw text of the
answer it came from, and ``removed``, the recovery classes (``parsing.RECOVERY_CLASSES``) that got from that
span to the caption; a request whose answer held a reasoning block, or whose server returned reasoning beside
the answer, keeps that text as ``reasoning``, apart from every caption. A request also keeps the server's
``finish_reason`` and ``response_model`` where the backend reports them, and ``problem``, the class of an answer
that holds no caption (``chat.ANSWER_PROBLEMS``). These fields are written only when they are not empty, so the
transcript of a clean answer from a backend that reports neither is the same file it always was.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import atomic_write_text, atomic_write_texts, load_json
from vlmproprio.locations import cell_name, transcript_path

ParseStatus = Literal["ok", "recovered", "missing"]
PARSE_STATUSES: tuple[str, ...] = ("ok", "recovered", "missing")
TRANSCRIPT_VERSION = 1


class TranscriptError(VlmproprioError):
    """A transcript file that cannot be read; the message names the file."""


@dataclass(frozen=True)
class FrameCaption:
    frame_index: int
    step: int
    text: str
    status: ParseStatus
    span: str = ""  # the raw text the caption came from; kept only when it was not "ok"
    removed: tuple[str, ...] = ()  # recovery classes applied, in the order met


@dataclass(frozen=True)
class SceneCaption:
    group: int
    frame_indices: tuple[int, ...]
    text: str
    status: ParseStatus
    span: str = ""
    removed: tuple[str, ...] = ()


@dataclass(frozen=True)
class RequestRecord:
    """One model call behind a transcript: which stage, which cache key, how it was answered."""

    stage: str  # "p1" | "p2" | "p3"
    group: int  # -1 for p3
    key: str
    from_cache: bool
    latency_s: float
    reasoning: str = ""  # the server's reasoning field, then the answer's reasoning block(s): never a caption
    finish_reason: str = ""  # why the server stopped ("stop", "length", ...), where the backend reports it
    response_model: str = ""  # the model the server says answered, where the backend reports it
    problem: str = ""  # why the answer holds no caption or may be another model's (chat.ANSWER_PROBLEMS)


_REQUEST_OPTIONAL = ("reasoning", "finish_reason", "response_model", "problem")


@dataclass
class Transcript:
    model: str
    episode_id: str
    task: str
    condition: str
    prompt_version: str
    frames: list[FrameCaption]
    scenes: list[SceneCaption]
    final: str
    final_status: ParseStatus
    requests: list[RequestRecord] = field(default_factory=list)
    final_span: str = ""
    final_removed: tuple[str, ...] = ()
    timing: dict[str, float] = field(default_factory=dict)
    version: int = TRANSCRIPT_VERSION

    @property
    def frame_texts(self) -> list[str]:
        return [f.text for f in self.frames]

    def to_dict(self) -> dict:
        # what dataclasses.asdict gives, built directly: its recursive deep copy cost ~0.4 ms per transcript
        return {
            "model": self.model,
            "episode_id": self.episode_id,
            "task": self.task,
            "condition": self.condition,
            "prompt_version": self.prompt_version,
            "frames": [
                {"frame_index": f.frame_index, "step": f.step, "text": f.text, "status": f.status}
                | _audit_fields(f.span, f.removed)
                for f in self.frames
            ],
            "scenes": [
                {"group": s.group, "frame_indices": tuple(s.frame_indices), "text": s.text, "status": s.status}
                | _audit_fields(s.span, s.removed)
                for s in self.scenes
            ],
            "final": self.final,
            "final_status": self.final_status,
            **{f"final_{k}": v for k, v in _audit_fields(self.final_span, self.final_removed).items()},
            "requests": [
                {"stage": r.stage, "group": r.group, "key": r.key, "from_cache": r.from_cache, "latency_s": r.latency_s}
                | {name: getattr(r, name) for name in _REQUEST_OPTIONAL if getattr(r, name)}
                for r in self.requests
            ],
            "timing": dict(self.timing),
            "version": self.version,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Transcript:
        d = dict(d)
        d["frames"] = [FrameCaption(**_read_audit(f)) for f in d["frames"]]
        d["scenes"] = [
            SceneCaption(**_read_audit({**s, "frame_indices": tuple(s["frame_indices"])})) for s in d["scenes"]
        ]
        d["requests"] = [RequestRecord(**r) for r in d.get("requests", [])]
        if "final_removed" in d:
            d["final_removed"] = tuple(d["final_removed"])
        return cls(**d)


def _audit_fields(span: str, removed: Sequence[str]) -> dict:
    """A caption's audit as written: only what is there (a clean caption's entry gains no key)."""
    out: dict = {}
    if span:
        out["span"] = span
    if removed:
        out["removed"] = list(removed)
    return out


def _read_audit(d: dict) -> dict:
    return {**d, "removed": tuple(d["removed"])} if "removed" in d else d


def answer_problems(transcripts: Sequence[Transcript]) -> dict[str, int]:
    """Requests per answer problem class over ``transcripts``, most frequent first."""
    counts: dict[str, int] = {}
    for t in transcripts:
        for r in t.requests:
            if r.problem:
                counts[r.problem] = counts.get(r.problem, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def frames_missing_by_problem(t: Transcript) -> int:
    """Frame captions of ``t`` that are missing and whose Process 1 answer had a problem (RequestRecord.problem)."""
    flagged = {r.group for r in t.requests if r.stage == "p1" and r.problem}
    if not flagged:
        return 0
    members = {i for s in t.scenes if s.group in flagged for i in s.frame_indices}
    return sum(1 for f in t.frames if f.status == "missing" and f.frame_index in members)


def cell_key(model: str, episode_id: str, condition: str) -> str:
    """One (model, episode, condition) cell: the key of its entry in scores/audit.json and traces.json, and its
    transcript's path below RUN_DIR/transcripts/ without the suffix."""
    return f"{model}/{cell_name(episode_id, condition)}"


def transcript_text(t: Transcript) -> str:
    """The transcript file's text: one space of indent per level, non-ASCII text as it is."""
    return json.dumps(t.to_dict(), indent=1, ensure_ascii=False) + "\n"


def write_transcript(run_dir: Path, t: Transcript) -> Path:
    path = transcript_path(run_dir, t.model, t.episode_id, t.condition)
    atomic_write_text(path, transcript_text(t))
    return path


def transcript_files(run_dir: Path, transcripts: Sequence[Transcript]) -> dict[Path, str]:
    """Each transcript's file in ``run_dir`` and its text, in ``transcripts`` order."""
    return {transcript_path(run_dir, t.model, t.episode_id, t.condition): transcript_text(t) for t in transcripts}


def write_transcripts(run_dir: Path, transcripts: Sequence[Transcript]) -> list[Path]:
    """``write_transcript`` for each, several at a time (``io.atomic_write_texts``); the first failure, in
    ``transcripts`` order, is raised once every write has finished or failed."""
    return list(atomic_write_texts(transcript_files(run_dir, transcripts)))


def read_transcript(path: Path) -> Transcript:
    return read_transcript_document(path)[0]


def read_transcript_document(path: Path) -> tuple[Transcript, dict]:
    """The transcript in ``path`` and the JSON object it was read from (left as parsed: from_dict copies)."""
    try:
        d = load_json(path, error=TranscriptError)
        if not isinstance(d, dict):
            raise TypeError("a transcript is a JSON object")
        if d.get("version") != TRANSCRIPT_VERSION:
            raise ValueError(f"version {d.get('version')!r}, expected {TRANSCRIPT_VERSION}")
        return Transcript.from_dict(d), d
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise TranscriptError(f"{path}: cannot read transcript ({type(exc).__name__}: {exc})") from exc


def read_transcripts(run_dir: Path, model: str | None = None) -> list[Transcript]:
    root = Path(run_dir) / "transcripts"
    pattern = f"{model}/*.json" if model else "*/*.json"
    return [read_transcript(p) for p in sorted(root.glob(pattern))]
