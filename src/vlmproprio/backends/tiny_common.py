"""What the tiny builds of vlmproprio.backends.tiny_families share: the family's tokenizer on the tiny BPE, the
text config on it, and the published repos' file layout (tokenizer, image processor, processor settings and
chat template, each in its file).

Without torchvision only the ``*ImageProcessorPil`` image processors exist, and processors that also declare a
video processor are loaded without it (vlmproprio.backends.hf_files); so, as in ``tiny._save_qwen``, such
processors are saved piece by piece rather than with ``processor.save_pretrained``.
"""

from __future__ import annotations

import json
from pathlib import Path

from vlmproprio.backends.tiny import _generation_config, _text_config, train_bpe

TEMPLATES = Path(__file__).with_name("chat_templates")
CONTEXT = 32768  # text positions: Process 3 of the 31-frame fixture episode is at most ~14k tokens (Gemma 3)


def chat_template(family: str) -> str:
    """The chat template of ``family``, as shipped in ``chat_templates/``."""
    return (TEMPLATES / f"{family}.jinja").read_text()


def family_tokenizer(
    *,
    bos: str | None,
    eos: str,
    pad: str,
    specials: tuple[str, ...] = (),
    named: dict[str, str] | None = None,
    seed: int = 0,
):
    """The tiny BPE with a family's special tokens: ``bos``/``eos``/``pad``, the chat ``specials`` and the
    ``named`` ones its processor reads off the tokenizer (``image_token``, ``boi_token``, ...)."""
    from transformers import Qwen2Tokenizer

    vocab, merges = train_bpe(seed)
    named = dict(named or {})
    tok = Qwen2Tokenizer(
        vocab=vocab,
        merges=merges,
        unk_token=None,
        bos_token=bos,
        eos_token=eos,
        pad_token=pad,
        model_max_length=CONTEXT,
        extra_special_tokens=named,
    )
    added = list(dict.fromkeys([*specials, *named.values()]))
    if added:
        tok.add_special_tokens({"additional_special_tokens": added}, replace_extra_special_tokens=False)
    tok.padding_side = "left"  # batched generation pads on the left
    return tok


def token_ids(tok, *tokens: str) -> list[int]:
    ids = [tok.convert_tokens_to_ids(t) for t in tokens]
    if any(i is None or i == tok.unk_token_id for i in ids):
        raise RuntimeError(f"tokens missing from the tiny tokenizer: {tokens} -> {ids}")
    return ids


def generation_config(tok, *ends: str):
    """Greedy generation that stops at any of ``ends`` (the family's end-of-turn tokens) or the pad token."""
    gen = _generation_config()
    gen.eos_token_id = token_ids(tok, *ends)
    gen.pad_token_id = tok.pad_token_id
    gen.bos_token_id = tok.bos_token_id
    return gen


def tiny_text_config(tok, *, context: int = CONTEXT, eos: str, **extra) -> dict:
    """The tiny text config on ``tok``: its vocabulary and special-token ids."""
    cfg = _text_config(len(tok), context=context, **extra)
    cfg.update(bos_token_id=tok.bos_token_id, eos_token_id=token_ids(tok, eos)[0], pad_token_id=tok.pad_token_id)
    return cfg


def tiny_vision_config(**extra) -> dict:
    """A tiny vision tower's size (2 layers, 4 heads, width 32), with the family's own keys in ``extra``."""
    return dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4, **extra)


def save_model(out: Path, model_cls, config, tok, ends: tuple[str, ...], seed: int) -> None:
    import torch

    torch.manual_seed(seed)
    model = model_cls(config).eval()
    model.generation_config = generation_config(tok, *ends)
    model.save_pretrained(out)


def save_pieces(out: Path, tok, image_processor, processor_class: str, template: str, **processor_config) -> None:
    """Tokenizer, image processor (with its ``processor_class``), the processor's own settings and the chat
    template, each in its file: the layout of the published repos, loadable without a video processor."""
    tok.chat_template = template
    tok.save_pretrained(out)
    image_processor.save_pretrained(out)
    pp = out / "preprocessor_config.json"
    data = json.loads(pp.read_text())
    data["processor_class"] = processor_class
    pp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    if processor_config:
        body = {**processor_config, "processor_class": processor_class}
        (out / "processor_config.json").write_text(json.dumps(body, indent=2, sort_keys=True) + "\n")
    (out / "chat_template.jinja").write_text(template)
