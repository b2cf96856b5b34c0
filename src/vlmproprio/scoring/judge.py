"""An optional judge model grading captions, and its agreement with the rubric.

Off by default: a backend grades captions; the rubric stays the reference and the agreement between the two
is reported (Cohen's kappa per item), so a judge never silently replaces auditable scores. The judge's
prompt is package data (``lexicons/judge.json``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from string import Template

from vlmproprio.chat import Answer, ChatRequest, GenerationConfig, Message, RequestTag, TextPart
from vlmproprio.episodes import Episode
from vlmproprio.scoring.expectation import Expectation, expectation_for
from vlmproprio.scoring.lexicon import LEXICON_PACKAGE, ScoringError, _read_lexicon_file
from vlmproprio.scoring.rubric import ITEMS, CaptionScore, ItemScore


@dataclass(frozen=True)
class JudgeVerdict:
    items: dict[str, ItemScore] | None  # None when the answer could not be parsed
    raw: str
    error: str = ""

    def to_dict(self) -> dict:
        items = None if self.items is None else {k: asdict(v) for k, v in self.items.items()}
        return {"items": items, "raw": self.raw, "error": self.error}


@lru_cache(maxsize=1)
def judge_prompt() -> dict:
    data, _ = _read_lexicon_file("judge.json")
    for k in ("system", "user", "actions", "max_new_tokens"):
        if k not in data:
            raise ScoringError(f"lexicon {LEXICON_PACKAGE}/judge.json: missing {k!r}")
    return data


_JUDGE_WORDS = {
    "robot_left": "to the robot's left",
    "robot_right": "to the robot's right",
    "left": "left in the image",
    "right": "right in the image",
    "forward": "forward (away from the robot)",
    "backward": "backward (toward the robot)",
}


def _trajectory_truth(exp: Expectation) -> str:
    """The ground truth a judge grades the trajectory against, in words (as expectation_for derives it)."""

    def words(ds: Sequence[str]) -> str:
        return " and ".join(_JUDGE_WORDS.get(d, d) for d in ds)

    parts = []
    for m in exp.motions:
        if m.expected:
            text = f"{m.name}: {words(m.expected)}"
            if m.returns:
                text += f" (afterwards it returns {words(m.returns)})"
            parts.append(text)
    if exp.target_row:
        column = (exp.target_column or "").replace("_", " ")
        side = f", {exp.image_side} in the image" if exp.image_side else ""
        parts.insert(
            0,
            f"the object goes to the {exp.target_row} compartment of the target bin on the robot's "
            f"{exp.target_side}{side} ({column} bin; near/far = from the robot)",
        )
    return "; ".join(parts) or "none"


def judge_request(text: str, episode: Episode, condition: str = ""):
    """The chat request asking a judge model to grade one caption of an episode."""
    prompt = judge_prompt()
    exp = expectation_for(episode)
    user = Template(prompt["user"]).safe_substitute(
        task=episode.task,
        instruction=episode.instruction,
        object=episode.target_object,
        action=prompt["actions"].get(episode.task, episode.action),
        trajectory=_trajectory_truth(exp),
        caption=text,
    )
    return ChatRequest(
        messages=(Message("system", (TextPart(prompt["system"]),)), Message("user", (TextPart(user),))),
        config=GenerationConfig(max_new_tokens=int(prompt["max_new_tokens"]), temperature=0.0),
        prompt_version=f"judge-v{prompt['version']}",
        tag=RequestTag(episode_id=episode.episode_id, condition=condition, stage="judge"),
    )


def parse_judge_answer(raw: str) -> JudgeVerdict:
    """Read the first JSON object in a judge's answer; anything unusable is a verdict with an error."""
    start = raw.find("{")
    if start < 0:
        return JudgeVerdict(None, raw, "no JSON object in the answer")
    try:
        data, _ = json.JSONDecoder().raw_decode(raw[start:])
        items = {}
        for item in ITEMS:
            d = data[item]
            mentioned, correct = d["mentioned"], d["correct"]
            if not isinstance(mentioned, bool) or not isinstance(correct, bool):
                raise TypeError(f"{item}: mentioned/correct must be true or false")
            items[item] = ItemScore(mentioned, correct and mentioned, mentioned and not correct)
    except (ValueError, KeyError, TypeError) as exc:
        return JudgeVerdict(None, raw, f"unusable answer ({type(exc).__name__}: {exc})")
    return JudgeVerdict(items, raw)


def judge_captions(
    answer: Callable[[Sequence[ChatRequest]], list[Answer]], captions: Sequence[tuple[str, Episode, str]]
) -> list[JudgeVerdict]:
    """Grade (text, episode, condition) triples, in order, with ``answer`` (a judge's ``Answerer.answer``, see
    vlmproprio.answering: its requests go through the same content-addressed response cache and cassettes as
    captioning, so a judge's verdicts replay bit-identically)."""
    requests = [judge_request(text, ep, cond) for text, ep, cond in captions]
    answers = answer(requests) if requests else []
    if len(answers) != len(requests):
        raise ScoringError(f"judge answered {len(answers)} of {len(requests)} requests")
    return [parse_judge_answer(a.text) for a in answers]


def _kappa(pairs: list[tuple[bool, bool]]) -> float | None:
    n = len(pairs)
    if not n:
        return None
    po = sum(1 for a, b in pairs if a == b) / n
    pa = sum(1 for a, _ in pairs if a) / n
    pb = sum(1 for _, b in pairs if b) / n
    pe = pa * pb + (1 - pa) * (1 - pb)
    return None if pe >= 1.0 else (po - pe) / (1 - pe)


def judge_agreement(rubric: Sequence[CaptionScore], verdicts: Sequence[JudgeVerdict]) -> dict:
    """Per item and field: how often judge and rubric agree, and Cohen's kappa; unparsed answers are counted."""
    if len(rubric) != len(verdicts):
        raise ValueError(f"{len(rubric)} rubric scores but {len(verdicts)} judge verdicts")
    usable = [(r, v) for r, v in zip(rubric, verdicts, strict=True) if v.items is not None]
    out: dict = {"n": len(rubric), "unparsed": len(rubric) - len(usable), "items": {}}
    for item in ITEMS:
        for what in ("mentioned", "correct"):
            pairs = [(getattr(r.item(item), what), getattr(v.items[item], what)) for r, v in usable]
            agree = sum(1 for a, b in pairs if a == b)
            out["items"][f"{item}_{what}"] = {
                "n": len(pairs),
                "agreement": agree / len(pairs) if pairs else None,
                "kappa": _kappa(pairs),
            }
    return out
