"""The request key's text laid out directly is the canonical JSON of the key document, byte for byte."""

from __future__ import annotations

import pytest

from vlmproprio.cache import canonical_json, key_document, key_text, request_key, sha256_text
from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart, Message, RequestTag, TextPart

IDENTITY = {"backend": "hf", "model_id": "m/x", "revision": "r", "dtype": "bf16", "extra": "ignored"}


def _requests() -> list[ChatRequest]:
    img = ImagePart(b"\x89PNG fake bytes")
    texts = ["plain", "", 'quotes " and \\ back', "line\nbreak\ttab", "ünïcödé ✓ 日本", "\x00\x1f control", "\u2028"]
    out = []
    for i, t in enumerate(texts):
        msgs = (
            Message("system", (TextPart("be brief"),)),
            Message("user", (TextPart(t), img, TextPart(t + " again"), ImagePart(b"x", mime="image/jpeg"))),
        )
        cfg = GenerationConfig(max_new_tokens=64 + i, temperature=0.5 * i, seed=i or None)
        out.append(ChatRequest(messages=msgs, config=cfg, prompt_version=f"v{i}é", tag=RequestTag("e", "c", "p1", i)))
    out.append(
        ChatRequest(messages=(), config=GenerationConfig(), prompt_version="", tag=RequestTag("e", "c", "p3", -1))
    )
    odd_mime = Message("user", (ImagePart(b"y", mime='image/"odd"\\ ✓\n'),))  # escapes in an image part's text
    out.append(ChatRequest(messages=(odd_mime,), config=GenerationConfig(), prompt_version="", tag=RequestTag()))
    return out


@pytest.mark.parametrize("request_", _requests())
def test_key_text_is_the_canonical_json_of_the_key_document(request_):
    for _ in range(2):  # the second time from remembered parts
        assert key_text(IDENTITY, request_) == canonical_json(key_document(IDENTITY, request_))
    assert request_key(IDENTITY, request_) == sha256_text(canonical_json(key_document(IDENTITY, request_)))


def test_key_text_of_pipeline_requests():
    from pathlib import Path

    from vlmproprio.conditions import frame_states, parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.pipeline import CellRun, PipelineSettings

    fixtures = Path(__file__).resolve().parents[1] / "fixtures"
    (ep,) = load_episodes(fixtures, ["bin1_00"], verify=False)
    images = [ImagePart(f.image_path.read_bytes()) for f in ep.frames]
    n = 0
    for cond in parse_conditions("all"):
        run = CellRun(ep, cond, images, frame_states(ep, cond, [ep]), PipelineSettings())
        for req in run.p1_requests():
            assert key_text(IDENTITY, req) == canonical_json(key_document(IDENTITY, req))
            n += 1
    assert n > 20
