"""Tiny random vision-language checkpoints, built offline and bit-for-bit reproducibly, for tests and CI.

Families with the real architectures and processors but a few hundred thousand random parameters
(``FAMILIES``). Built here: ``qwen2-vl`` (Qwen2VLForConditionalGeneration), ``qwen2.5-vl`` and ``llava`` (a
CLIP vision tower on a Qwen2 language model); the others (Qwen3-VL, Gemma 3, Idefics3, InternVL,
LLaVA-OneVision, Mistral 3, GLM-4.1V, Mllama, LLaVA-NeXT, Idefics2) by vlmproprio.backends.tiny_families, with their chat templates
as data files (docs/models.md lists them and what each keeps of the published geometry).
The tokenizer is a byte-level BPE trained here on synthetic robot-prompt text,
with the Qwen2 pre-tokenizer and special tokens; the chat templates follow the
real models' (written from their published logic, an approximation). The
image processors keep the real geometry (Qwen2-VL: 14 px patches merged 2x2,
so a 256x256 frame is 81 image tokens), so prompt shapes match the real models.

Their text is gibberish by nature: they exercise the real code path and make
regression gates deterministic, nothing more. A build with the same seed and
the same torch/transformers/tokenizers versions gives sha256-identical files.

``ensure_tiny_model(family)`` builds a family once per machine into
``<cache root>/models`` ($VLMPROPRIO_CACHE, default ``~/.cache/vlmproprio``), safely
when several processes ask at once (build in a temporary folder, then an
atomic rename; the loser of the race uses the winner's build).
"""

from __future__ import annotations

import json
import os
import random
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from vlmproprio.backends.base import BackendError
from vlmproprio.backends.hf_files import STAMP_FILE
from vlmproprio.episodes import sha256_file

# The first three are built here; the others by vlmproprio.backends.tiny_families (same tokenizer, sizes, layout).
FAMILIES: tuple[str, ...] = (
    "qwen2-vl",
    "qwen2.5-vl",
    "llava",
    "qwen3-vl",
    "gemma3",
    "idefics3",
    "internvl",
    "llava-onevision",
    "mistral3",
    "glm4v",
    "mllama",
    "llava-next",
    "idefics2",
    "smolvlm",
)
BUILD_VERSION = 3  # 2: the LLaVA build's context holds Process 3 at the image cap; 3: the Qwen builds' too

# Order fixes the token ids 0..6 (the real Qwen2 tokenizer has them at 151643..151656).
SPECIAL_TOKENS = (
    "<|endoftext|>",  # 0: pad
    "<|im_start|>",  # 1
    "<|im_end|>",  # 2: end of a chat turn (eos)
    "<|vision_start|>",  # 3
    "<|vision_end|>",  # 4
    "<|image_pad|>",  # 5
    "<|video_pad|>",  # 6
)
LLAVA_IMAGE_TOKEN = "<image>"
# The split regex of transformers' Qwen2 tokenizer.
QWEN2_PRETOKENIZE_REGEX = r"""(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+"""

# The logic of Qwen/Qwen2-VL-*-Instruct's chat template (also used by Qwen2.5-VL).
QWEN_CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% set video_count = namespace(value=0) %}"
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}"
    "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n{% endif %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n"
    "{% else %}{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'video' or 'video' in content %}"
    "{% set video_count.value = video_count.value + 1 %}"
    "{% if add_vision_id %}Video {{ video_count.value }}: {% endif %}"
    "<|vision_start|><|video_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n"
    "{% endif %}{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)
LLAVA_CHAT_TEMPLATE = (
    "{% for m in messages %}<|im_start|>{{ m['role'] }}\n{% if m['content'] is string %}{{ m['content'] }}"
    "{% else %}{% for c in m['content'] %}{% if c['type'] == 'image' %}<image>\n{% else %}{{ c['text'] }}"
    "{% endif %}{% endfor %}{% endif %}<|im_end|>\n{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

_CORPUS_WORDS = (
    "the robot arm gripper moves grasps picks places pushes pulls opens closes rotates lifts lowers turns "
    "cereal box bin door handle lever latch table compartment towards away forward backward left right up down "
    "joint angles end effector frame frames image camera scene describe what is happening in this step task "
    "approach contact release success instruction caption process group first then finally near far"
)


def _corpus(seed: int, n: int = 4000) -> Iterator[str]:
    """Synthetic text shaped like vlmproprio prompts and captions, to train the tiny BPE on."""
    rng = random.Random(seed)
    words = _CORPUS_WORDS.split()
    for _ in range(n):
        kind = rng.random()
        if kind < 0.4:
            yield " ".join(rng.choice(words) for _ in range(rng.randint(5, 15))) + "."
        elif kind < 0.75:
            joints = ", ".join(f"{rng.uniform(-3.14, 3.14):.3f}" for _ in range(8))
            ee = ", ".join(f"{rng.uniform(-1.5, 1.5):.3f}" for _ in range(6))
            yield f"Frame {rng.randint(1, 5)}: joint angles [{joints}]; end-effector [{ee}]"
        else:
            yield f"# Process {rng.randint(1, 3)}\nFrame {rng.randint(1, 5)}: " + " ".join(rng.sample(words, 6))


def train_bpe(seed: int = 0, vocab_size: int = 1024) -> tuple[dict[str, int], list[tuple[str, str]]]:
    """The vocabulary and merges of a byte-level BPE (no unknown tokens) trained on ``_corpus``, with the Qwen2
    pre-tokenizer; ``SPECIAL_TOKENS`` are its ids 0..6."""
    from tokenizers import Regex, Tokenizer, decoders, models, normalizers, pre_tokenizers, trainers

    bpe = Tokenizer(models.BPE())
    bpe.normalizer = normalizers.NFC()
    bpe.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN2_PRETOKENIZE_REGEX), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=list(SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),  # all 256 bytes: nothing is out of vocabulary
        show_progress=False,
    )
    bpe.train_from_iterator(_corpus(seed), trainer=trainer)
    merges = [
        tuple(m) if isinstance(m, list) else tuple(m.split(" ")) for m in json.loads(bpe.to_str())["model"]["merges"]
    ]
    return bpe.get_vocab(), merges


def build_tokenizer(seed: int = 0, vocab_size: int = 1024):
    """A Qwen2 tokenizer (byte-level BPE, no unknown tokens) trained on ``_corpus``."""
    from transformers import Qwen2Tokenizer

    vocab, merges = train_bpe(seed, vocab_size)
    tok = Qwen2Tokenizer(
        vocab=vocab,
        merges=merges,
        unk_token=None,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
        model_max_length=32768,
    )
    tok.add_special_tokens({"additional_special_tokens": list(SPECIAL_TOKENS[1:])})
    tok.padding_side = "left"  # batched generation pads on the left
    ids = [tok.convert_tokens_to_ids(t) for t in SPECIAL_TOKENS]
    if ids != list(range(len(SPECIAL_TOKENS))):
        raise RuntimeError(f"special token ids moved: {ids}")  # a tokenizers change; the configs below assume 0..6
    return tok


def _text_config(vocab_size: int, context: int = 4096, **extra) -> dict:
    return dict(
        vocab_size=vocab_size,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,  # head_dim 16 -> rotary half-dim 8
        num_key_value_heads=2,
        max_position_embeddings=context,
        bos_token_id=0,
        eos_token_id=2,
        pad_token_id=0,
        **extra,
    )


def _generation_config():
    from transformers import GenerationConfig

    return GenerationConfig(do_sample=False, eos_token_id=[2, 0], pad_token_id=0, bos_token_id=0)


# The vision towers of the tiny Qwen families (merger output 64 = the text hidden size), and what they share.
_QWEN_VISION = {
    "qwen2-vl": dict(depth=2, embed_dim=32, num_heads=4, mlp_ratio=2, hidden_size=64, in_channels=3),
    "qwen2.5-vl": dict(
        depth=2,
        hidden_size=32,
        intermediate_size=64,
        num_heads=4,
        out_hidden_size=64,
        fullatt_block_indexes=[1],
        window_size=112,
    ),
}
_QWEN_PATCHES = dict(patch_size=14, spatial_merge_size=2, temporal_patch_size=2)


def _save_qwen(out: Path, family: str, seed: int) -> None:
    import torch
    from transformers import (
        Qwen2_5_VLConfig,
        Qwen2_5_VLForConditionalGeneration,
        Qwen2VLConfig,
        Qwen2VLForConditionalGeneration,
        Qwen2VLImageProcessorPil,
    )

    tok = build_tokenizer(seed)
    tok.chat_template = QWEN_CHAT_TEMPLATE
    mrope = {"rope_type": "default", "rope_theta": 1_000_000.0, "mrope_section": [2, 3, 3]}  # sums to head_dim/2
    config_cls, model_cls = {
        "qwen2-vl": (Qwen2VLConfig, Qwen2VLForConditionalGeneration),
        "qwen2.5-vl": (Qwen2_5_VLConfig, Qwen2_5_VLForConditionalGeneration),
    }[family]
    config = config_cls(
        # the real models' context (32k for Qwen2-VL, 128k for Qwen2.5-VL) holds Process 3 at the image cap, and
        # the hf backend refuses a prompt past the config's: 4,096 would refuse the longest fixture episodes
        text_config=_text_config(len(tok), context=32768, rope_parameters=mrope),
        vision_config={**_QWEN_VISION[family], **_QWEN_PATCHES},
        tie_word_embeddings=False,
        image_token_id=5,
        video_token_id=6,
        vision_start_token_id=3,
        vision_end_token_id=4,
    )
    torch.manual_seed(seed)
    model = model_cls(config).eval()
    model.generation_config = _generation_config()
    model.save_pretrained(out)
    tok.save_pretrained(out)
    # Saved piece by piece, in the real repos' layout: without torchvision there is no video processor,
    # so the processor object itself cannot be built or saved here.
    image_processor = Qwen2VLImageProcessorPil(min_pixels=56 * 56, max_pixels=28 * 28 * 1280)
    image_processor.save_pretrained(out)
    pp = out / "preprocessor_config.json"
    data = json.loads(pp.read_text())
    data["processor_class"] = "Qwen2_5_VLProcessor" if family == "qwen2.5-vl" else "Qwen2VLProcessor"
    pp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    (out / "chat_template.jinja").write_text(QWEN_CHAT_TEMPLATE)


def _save_llava(out: Path, seed: int) -> None:
    import torch
    from transformers import CLIPImageProcessorPil, LlavaConfig, LlavaForConditionalGeneration, LlavaProcessor

    tok = build_tokenizer(seed)
    tok.add_special_tokens({"additional_special_tokens": [*SPECIAL_TOKENS[1:], LLAVA_IMAGE_TOKEN]})
    tok.chat_template = LLAVA_CHAT_TEMPLATE
    config = LlavaConfig(
        vision_config=dict(
            model_type="clip_vision_model",
            hidden_size=32,
            intermediate_size=64,
            num_hidden_layers=2,
            num_attention_heads=4,
            image_size=224,
            patch_size=14,
            projection_dim=32,
        ),
        # 257 tokens a frame: Process 3 with 31 images and the state text is ~14,500 tokens. A server refuses a
        # prompt longer than the model's context (transformers serve does), so the config must hold it.
        text_config=dict(model_type="qwen2", **_text_config(len(tok), context=32768)),
        image_token_id=tok.convert_tokens_to_ids(LLAVA_IMAGE_TOKEN),
        vision_feature_select_strategy="default",
        vision_feature_layer=-2,
        projector_hidden_act="gelu",
    )
    torch.manual_seed(seed)
    model = LlavaForConditionalGeneration(config).eval()
    model.generation_config = _generation_config()
    image_processor = CLIPImageProcessorPil(size={"shortest_edge": 224}, crop_size={"height": 224, "width": 224})
    processor = LlavaProcessor(
        image_processor=image_processor,
        tokenizer=tok,
        patch_size=14,
        vision_feature_select_strategy="default",
        num_additional_image_tokens=1,
        chat_template=LLAVA_CHAT_TEMPLATE,
    )
    model.save_pretrained(out)
    processor.save_pretrained(out)  # LLaVA has no video processor: the ordinary save/load round-trips


def file_hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file in ``folder`` (recursively), by relative POSIX path."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): sha256_file(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def check_family(family: str) -> str:
    if family not in FAMILIES:
        raise BackendError(f"unknown tiny model family {family!r}; choose from {', '.join(FAMILIES)}")
    return family


def build_tiny_model(family: str, out_dir: Path | str, *, seed: int = 0) -> Path:
    """Build the tiny ``family`` checkpoint into ``out_dir`` (created; existing files are overwritten)."""
    check_family(family)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    if family == "llava":
        _save_llava(out, seed)
    elif family in ("qwen2-vl", "qwen2.5-vl"):
        _save_qwen(out, family, seed)
    else:
        from vlmproprio.backends.tiny_families import BUILDERS

        BUILDERS[family](out, seed)
    for p in out.rglob("*"):  # save_pretrained writes some files 0600; the same mode everywhere keeps builds equal
        if p.is_file():
            p.chmod(0o644)
    stamp = {"family": family, "seed": seed, "build_version": BUILD_VERSION, "files": file_hashes(out)}
    (out / STAMP_FILE).write_text(json.dumps(stamp, indent=1, sort_keys=True) + "\n")
    return out


def models_dir(home: Path | None = None) -> Path:
    """The models/ folder of the cache root ``home`` (None: vlmproprio.locations.cache_root()): the tiny builds,
    and the memo of local model folders' revisions."""
    from vlmproprio.locations import cache_root

    return cache_root(home) / "models"


def tiny_model_dir(family: str, home: Path | None = None) -> Path:
    check_family(family)
    return models_dir(home) / f"tiny-{family}-b{BUILD_VERSION}"


def _valid_build(folder: Path, family: str) -> bool:
    try:
        stamp = json.loads((folder / STAMP_FILE).read_text())
    except (OSError, ValueError):
        return False
    return stamp.get("family") == family and stamp.get("build_version") == BUILD_VERSION and stamp.get("seed") == 0


def ensure_tiny_model(family: str, home: Path | None = None) -> Path:
    """The folder of the tiny ``family`` checkpoint, built on first use (seed 0); safe under concurrency."""
    final = tiny_model_dir(family, home)
    if _valid_build(final, family):
        verify_tiny_model(final)
        return final
    if final.exists():
        raise BackendError(
            f"{final} exists but is not a complete tiny {family} build (no valid {STAMP_FILE}); delete it to rebuild"
        )
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.building-"))
    try:
        build_tiny_model(family, tmp, seed=0)
        try:
            os.rename(tmp, final)  # atomic; fails if another process got there first
        except OSError:
            if not _valid_build(final, family):
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def verify_tiny_model(folder: Path) -> None:
    """Check a build against the hashes in its stamp (a damaged file would silently change every answer)."""
    folder = Path(folder)
    try:
        stamp = json.loads((folder / STAMP_FILE).read_text())
        expected = stamp["files"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BackendError(f"{folder}: no readable {STAMP_FILE} ({exc}); delete the folder to rebuild") from exc
    actual = {k: v for k, v in file_hashes(folder).items() if k != STAMP_FILE}
    if actual != expected:
        bad = sorted(k for k in set(actual) | set(expected) if actual.get(k) != expected.get(k))
        raise BackendError(f"{folder}: files differ from their build stamp ({', '.join(bad)}); delete it to rebuild")
