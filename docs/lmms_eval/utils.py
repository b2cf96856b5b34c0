"""lmms-eval task functions for vlmproprio's exported episodes (see vlmproprio_frames.yaml).

Every piece of the method comes from vlmproprio itself: the prompt text (``vlmproprio.prompts``), the answer
parser (``vlmproprio.parsing``) and the segmentation score (``vlmproprio.embeddings`` + ``vlmproprio.segmentation``),
so a caption scores here as it scores in ``vlmproprio score``. Needs ``pip install 'vlmproprio[embed]'`` next
to lmms-eval.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from vlmproprio import parsing, prompts
from vlmproprio.chat import ImagePart, TextPart
from vlmproprio.conditions import PAPER_CONDITIONS, get_condition
from vlmproprio.segmentation import DEFAULT_THRESHOLD, caption_present, cosine_trace, evaluate_segmentation

# A frame's label ("Image 1:") is rendered only for a frame with an image; lmms-eval sends the image itself.
_IMAGE_SLOT = ImagePart(b"")


def _options(kwargs: dict | None) -> tuple:
    kw = kwargs or {}
    name = kw.get("condition", "both")
    if name not in PAPER_CONDITIONS:
        raise ValueError(f"condition {name!r}: one frame's own state gives only {', '.join(PAPER_CONDITIONS)}")
    return get_condition(name), prompts.PromptOptions(example=bool(kw.get("example", True)))


def doc_to_visual(doc: dict) -> list:
    return [doc["image"].convert("RGB")]


def doc_to_text(doc: dict, lmms_eval_specific_kwargs: dict | None = None) -> str:
    """The paper's Process 1 prompt for a group of one frame, as vlmproprio renders it."""
    condition, options = _options(lmms_eval_specific_kwargs)
    state = prompts.state_text(1, condition, np.asarray(doc["joints"]), np.asarray(doc["ee"]))
    [message] = prompts.process1([prompts.FrameView(1, _IMAGE_SLOT, state)], condition, options)
    return "".join(p.text for p in message.parts if isinstance(p, TextPart))


def process_results(doc: dict, results: list[str]) -> dict:
    [caption] = parsing.parse_frame_captions(results[0], 1)
    item = {
        "episode_id": doc["episode_id"],
        "frame_index": doc["frame_index"],
        "phase": doc["phase"],
        "caption": caption.text,
        "status": caption.status,
    }
    return {"vlmproprio_seg_f1_tol1": item, "vlmproprio_seg_edit": item}


def segmentation_by_episode(items: list[dict], threshold: float = DEFAULT_THRESHOLD) -> dict[str, dict]:
    """vlmproprio's segmentation of each episode's frame captions: {episode_id: SweepPoint.flat()}."""
    from vlmproprio.embeddings import CachedEmbedder, EmbeddingStore, default_embedding_dir, encoder_spec

    episodes: dict[str, list[dict]] = defaultdict(list)
    for it in items:
        episodes[it["episode_id"]].append(it)
    texts = sorted({it["caption"] for it in items if caption_present(it["caption"], it["status"])})
    with EmbeddingStore(default_embedding_dir()) as store:
        vectors = CachedEmbedder(encoder_spec(), store).embed(texts)
    out = {}
    for eid, frames in sorted(episodes.items()):
        frames.sort(key=lambda it: it["frame_index"])
        present = [caption_present(it["caption"], it["status"]) for it in frames]
        trace = cosine_trace([vectors[it["caption"]] if ok else None for it, ok in zip(frames, present, strict=True)])
        out[eid] = evaluate_segmentation(trace, [it["phase"] for it in frames], threshold).flat()
    return out


def _mean_over_episodes(items: list[dict], key: str) -> float:
    values = [v[key] for v in segmentation_by_episode(items).values() if v[key] is not None]
    return math.fsum(values) / len(values) if values else float("nan")


def aggregate_seg_f1_tol1(items: list[dict]) -> float:
    return _mean_over_episodes(items, "f1_tol1")


def aggregate_seg_edit(items: list[dict]) -> float:
    return _mean_over_episodes(items, "edit")
