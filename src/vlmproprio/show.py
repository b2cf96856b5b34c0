"""The full prompt of every request of one (episode, condition) of a run, re-rendered (the show command).

The response cache and the transcripts store request keys, not prompts. A prompt is a function of the
fixtures, the condition, the pipeline settings recorded in run.json and the answers of the earlier processes
(recorded in the transcript), so it can be rebuilt exactly; each rebuilt request's cache key is compared with
the key the run recorded, which proves the prompt shown is the prompt that was sent (or says it is not,
e.g. after the prompts or the fixtures changed). Below each answer it lists how the parser got each caption
that was not in the exact requested form (its status, the recovery classes removed, the raw span it came
from) and the answer's reasoning, when the model wrote any.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vlmproprio import prompts
from vlmproprio.cache import request_key
from vlmproprio.chat import ANSWER_PROBLEMS, ChatRequest, ImagePart
from vlmproprio.conditions import frame_states, get_condition
from vlmproprio.episodes import frame_images, load_episodes
from vlmproprio.errors import UsageError
from vlmproprio.io import load_required_json
from vlmproprio.parsing import Parsed
from vlmproprio.pipeline import CellRun, PipelineSettings
from vlmproprio.transcripts import FrameCaption, SceneCaption, Transcript, read_transcripts


@dataclass(frozen=True)
class ShownRequest:
    request: ChatRequest
    key: str  # the key of the rebuilt request
    recorded_key: str | None  # the key the run recorded for this stage and group
    answer: str  # the parsed answer the run kept (frame captions joined for Process 1)
    audit: tuple[str, ...] = ()  # one line per caption not taken as it was, then the answer's reasoning

    @property
    def matches(self) -> bool:
        return self.recorded_key == self.key


def _run_manifest(run_dir: Path) -> dict:
    path = run_dir / "run.json"
    # the bounded loader: damaged or deeply nested JSON is one line naming the file
    missing = f"{path}: missing; is {run_dir} a run directory (`vlmproprio run --model NAME --out {run_dir}`)?"
    data = load_required_json(path, missing, error=UsageError)
    if not isinstance(data, dict) or not isinstance(data.get("models"), list):
        raise UsageError(f"{path}: not a run manifest")
    return data


def _pick_model(manifest: dict, model: str | None, where: Path) -> dict:
    models = [m for m in manifest["models"] if isinstance(m, dict)]
    names = ", ".join(str(m.get("name")) for m in models) or "none"
    if model is None:
        if len(models) != 1:
            raise UsageError(f"{where}: the run holds models {names}; choose one with --model")
        return models[0]
    for m in models:
        if model in (m.get("name"), m.get("slug")):
            return m
    raise UsageError(f"{where}: no model {model!r} in the run (it holds: {names})")


def rerender(
    run_dir: str | Path,
    episode_id: str,
    condition: str,
    *,
    model: str | None = None,
    fixtures: str | Path | None = None,
) -> list[ShownRequest]:
    """Every request of (episode, condition) of ``model`` in the run, in the order they were sent."""
    run_dir = Path(run_dir)
    manifest = _run_manifest(run_dir)
    m = _pick_model(manifest, model, run_dir / "run.json")
    settings = PipelineSettings.from_dict(m["pipeline"])
    version = prompts.prompt_version(settings.prompt)
    if version != m["pipeline"].get("prompt_version"):
        raise UsageError(
            f"the run used prompts {m['pipeline'].get('prompt_version')!r}, this vlmproprio has {version!r}: "
            "the prompts cannot be re-rendered as they were sent"
        )
    root = Path(fixtures) if fixtures is not None else Path(str(manifest.get("fixtures", "")))
    transcripts = [
        t for t in read_transcripts(run_dir, m["slug"]) if (t.episode_id, t.condition) == (episode_id, condition)
    ]
    if not transcripts:
        raise UsageError(
            f"{run_dir}: no transcript of {m['name']} for episode {episode_id!r} under condition {condition!r} "
            f"(episodes: {', '.join(manifest.get('episodes', []))}; conditions: {', '.join(manifest.get('conditions', []))})"
        )
    t = transcripts[0]
    peers = load_episodes(root)  # both_shuffled borrows another episode's states, as the run did
    episode = next(e for e in peers if e.episode_id == episode_id)
    cond = get_condition(condition)
    images = [ImagePart(data) for data in frame_images(episode.frames)]
    cell = CellRun(episode, cond, images, frame_states(episode, cond, peers), settings)
    recorded = {(r.stage, r.group): r.key for r in t.requests}
    identity = m.get("identity", {})
    frames = {f.frame_index: f for f in t.frames}

    p1 = cell.p1_requests()
    cell.frame_captions = [
        Parsed(frames[i].text, frames[i].status) if i in frames else Parsed("", "missing")
        for i in range(len(cell.positions))
    ]
    p1_answers = [" | ".join(cell.frame_captions[i].text for i in members) for members in cell.groups]
    p2 = cell.p2_requests()
    cell.scene_captions = [Parsed(s.text, s.status) for s in t.scenes]
    p3 = cell.p3_request()
    # settings that no longer fit the transcript (other groups) still render; their keys then differ
    scene_texts = [sc.text for sc in t.scenes]
    answers = [*p1_answers, *(scene_texts[g] if g < len(scene_texts) else "" for g in range(len(p2)))]
    shown = [
        ShownRequest(
            req,
            request_key(identity, req),
            recorded.get((req.tag.stage, req.tag.group)),
            answer,
            _audit_lines(t, req.tag.stage, req.tag.group, cell.groups),
        )
        for req, answer in zip([*p1, *p2], answers, strict=True)
    ]
    p3_audit = _audit_lines(t, "p3", -1, cell.groups)
    shown.append(ShownRequest(p3, request_key(identity, p3), recorded.get(("p3", -1)), t.final, p3_audit))
    return shown


def _caption_line(name: str, status: str, span: str, removed: tuple[str, ...]) -> str | None:
    if not span and not removed:
        return None
    classes = f" ({', '.join(removed)} removed)" if removed else ""
    return f"{name}: {status}{classes}, from: {span!r}"


def _audit_lines(t: Transcript, stage: str, group: int, groups: list[range]) -> tuple[str, ...]:
    """The audit of one request's captions as the transcript kept it, and its reasoning."""
    lines: list[str | None] = []
    if stage == "p1" and group < len(groups):
        frames: dict[int, FrameCaption] = {f.frame_index: f for f in t.frames}
        got = [frames[i] for i in groups[group] if i in frames]
        lines += [_caption_line(f"frame {f.frame_index}", f.status, f.span, f.removed) for f in got]
    elif stage == "p2":
        scenes: list[SceneCaption] = [s for s in t.scenes if s.group == group]
        lines += [_caption_line(f"scene {s.group}", s.status, s.span, s.removed) for s in scenes]
    elif stage == "p3":
        lines.append(_caption_line("final", t.final_status, t.final_span, t.final_removed))
    record = next((r for r in t.requests if (r.stage, r.group) == (stage, group)), None)
    if record is not None and record.problem:
        what = ANSWER_PROBLEMS.get(record.problem, "")
        lines.append(
            f"answer problem: {record.problem} ({what}); finish reason {record.finish_reason or 'none'}, "
            f"response model {record.response_model or 'not given'}"
        )
    reasoning = record.reasoning if record is not None else ""
    if reasoning:
        lines.append(f"reasoning ({len(reasoning)} characters, no part of any caption): {reasoning}")
    return tuple(line for line in lines if line is not None)


def format_shown(shown: list[ShownRequest]) -> str:
    """The requests as text: each message's role and full text, images as <image sha256>."""
    out = []
    for s in shown:
        tag = s.request.tag
        group = f" group {tag.group}" if tag.group >= 0 else ""
        check = "matches the run" if s.matches else f"DIFFERS from the run's {s.recorded_key or 'none'}"
        out.append(f"===== {tag.stage}{group}: key {s.key[:16]} ({check})")
        for msg in s.request.messages:
            out.append(f"--- [{msg.role}]")
            for part in msg.parts:
                if isinstance(part, ImagePart):
                    out.append(f"<image {part.sha256[:16]}, {len(part.data)} bytes>")
                else:
                    out.append(part.text)
        out.append(f"--- answer kept by the run: {s.answer}")
        out += [f"--- parsed: {line}" for line in s.audit]
        out.append("")
    return "\n".join(out)
