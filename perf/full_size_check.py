"""Full-size VLM architectures without their weights: what one Process-1 and one Process-3 request cost.

    python perf/full_size_check.py --tokens-only smolvlm-256m        # three families, CPU: ~30 min on 2 busy cores
    python perf/full_size_check.py --family smolvlm-256m --tokens-only smolvlm-256m   # P3 counted, not run

Models: Qwen2-VL-2B-Instruct, Qwen2.5-VL-3B-Instruct and SmolVLM-256M-Instruct (Idefics3), each built from its
published config.json (the values typed in below) with random bf16 weights: no weights can be downloaded, and
memory, context and token counts do not depend on their values. Each family's image processor is built with its
published preprocessor_config.json values (the ``*ImageProcessorPil`` classes: there is no torchvision), and its
processor class is the family's own (without the video part, as vlmproprio.backends.hf_files loads it).

Text tokens: there is no real tokenizer here, so text comes from the suite's tiny byte-level BPE
(vlmproprio.backends.tiny.build_tokenizer) unless ``--processor-dir FAMILY=DIR`` gives a real processor folder.
Text token counts are therefore approximate; image tokens are exact (they come from the image processor's
geometry and the processor's expansion of each image placeholder).

Requests: made by the suite's pipeline, as perf/gpu_throughput.py's ``pipeline_waves`` makes them (the reference
captioner answers Processes 1 and 2, so Process 3's prompt has its real shape), for one fixture episode and
condition. Each request runs through HFBackend.generate on the CPU with ``max_new_tokens=1`` (one prefill).

Peak memory: the process's resident-set high-water mark (VmHWM), reset before each request
(``/proc/self/clear_refs``), so each row's peak includes the weights resident at that time.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from _common import FIXTURES, emit, machine, table, write_json
from gpu_throughput import QWEN2VL_2B_TEXT, QWEN2VL_2B_VISION, weight_bytes

# Qwen/Qwen2.5-VL-3B-Instruct, config.json as published (3.75 B parameters)
QWEN25VL_3B_TEXT = dict(
    vocab_size=151936,
    hidden_size=2048,
    intermediate_size=11008,
    num_hidden_layers=36,
    num_attention_heads=16,
    num_key_value_heads=2,
    max_position_embeddings=128000,
    rms_norm_eps=1e-6,
    hidden_act="silu",
    tie_word_embeddings=True,
    rope_parameters={"rope_type": "default", "rope_theta": 1000000.0, "mrope_section": [16, 24, 24]},
)
QWEN25VL_3B_VISION = dict(
    depth=32,
    hidden_size=1280,
    intermediate_size=3420,
    hidden_act="silu",
    num_heads=16,
    in_channels=3,
    out_hidden_size=2048,
    patch_size=14,
    spatial_merge_size=2,
    temporal_patch_size=2,
    window_size=112,
    fullatt_block_indexes=[7, 15, 23, 31],
    tokens_per_second=2,
)
# Qwen2-VL-2B-Instruct and Qwen2.5-VL-3B-Instruct preprocessor_config.json (Qwen2VLImageProcessor)
QWEN_IMAGE_PROCESSOR = dict(
    min_pixels=3136,
    max_pixels=12845056,
    patch_size=14,
    temporal_patch_size=2,
    merge_size=2,
    image_mean=[0.48145466, 0.4578275, 0.40821073],
    image_std=[0.26862954, 0.26130258, 0.27577711],
)
# HuggingFaceTB/SmolVLM-256M-Instruct, config.json (Idefics3: SigLIP-B/16 at 512 px + SmolLM2-135M)
SMOLVLM_256M_TEXT = dict(
    model_type="llama",
    vocab_size=49280,
    hidden_size=576,
    intermediate_size=1536,
    num_hidden_layers=30,
    num_attention_heads=9,
    num_key_value_heads=3,
    head_dim=64,
    max_position_embeddings=8192,
    rms_norm_eps=1e-5,
    hidden_act="silu",
    tie_word_embeddings=False,
    rope_parameters={"rope_type": "default", "rope_theta": 100000.0},
)
SMOLVLM_256M_VISION = dict(
    hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12, patch_size=16, image_size=512
)
# its preprocessor_config.json and processor_config.json (image_seq_len)
SMOLVLM_IMAGE_PROCESSOR = dict(
    do_image_splitting=True,
    max_image_size={"longest_edge": 512},
    size={"longest_edge": 2048},
    resample=1,
    image_mean=[0.5, 0.5, 0.5],
    image_std=[0.5, 0.5, 0.5],
)
SMOLVLM_IMAGE_SEQ_LEN = 64
# The logic of SmolVLM-Instruct's chat template.
SMOLVLM_CHAT_TEMPLATE = (
    "<|im_start|>{% for message in messages %}{{ message['role'] | capitalize }}"
    "{% if message['content'][0]['type'] == 'image' %}{{ ':' }}{% else %}{{ ': ' }}{% endif %}"
    "{% for line in message['content'] %}{% if line['type'] == 'text' %}{{ line['text'] }}"
    "{% elif line['type'] == 'image' %}{{ '<image>' }}{% endif %}{% endfor %}<end_of_utterance>\n{% endfor %}"
    "{% if add_generation_prompt %}{{ 'Assistant:' }}{% endif %}"
)


@dataclass(frozen=True)
class Family:
    name: str
    checkpoint: str  # the published checkpoint whose config is typed in above
    build: Callable[[object], tuple[object, object]]  # processor -> (model, processor)
    processor: Callable[[], object]  # the family's processor, with the tiny tokenizer
    image_token: str
    context: int  # max_position_embeddings of the published config


# ---------------------------------------------------------------------------------------------- processors


def qwen_processor(cls_name: str) -> Callable[[], object]:
    def make():
        import transformers
        from transformers import Qwen2VLImageProcessorPil

        from vlmproprio.backends.hf_files import _image_only
        from vlmproprio.backends.tiny import QWEN_CHAT_TEMPLATE, build_tokenizer

        tok = build_tokenizer()
        cls = _image_only(getattr(transformers, cls_name))
        image_processor = Qwen2VLImageProcessorPil(**QWEN_IMAGE_PROCESSOR)
        return cls(image_processor=image_processor, tokenizer=tok, chat_template=QWEN_CHAT_TEMPLATE)

    return make


def smolvlm_processor():
    from transformers import Idefics3ImageProcessorPil, Idefics3Processor

    from vlmproprio.backends.tiny import build_tokenizer

    tok = build_tokenizer()
    grid = [f"<row_{i}_col_{j}>" for i in range(1, 7) for j in range(1, 7)]
    tok.add_special_tokens({"additional_special_tokens": ["<global-img>", *grid]}, replace_extra_special_tokens=False)
    image_processor = Idefics3ImageProcessorPil(**SMOLVLM_IMAGE_PROCESSOR)
    return Idefics3Processor(
        image_processor=image_processor,
        tokenizer=tok,
        image_seq_len=SMOLVLM_IMAGE_SEQ_LEN,
        chat_template=SMOLVLM_CHAT_TEMPLATE,
    )


# ---------------------------------------------------------------------------------------------- models


def random_model(config):
    """The architecture of ``config`` with random bf16 weights (seed 0), greedy, on the CPU."""
    import torch
    from transformers import AutoModelForImageTextToText

    torch.manual_seed(0)
    model = AutoModelForImageTextToText.from_config(config, dtype=torch.bfloat16, attn_implementation="sdpa")
    return model.eval()


def build_qwen(config_cls_name: str, text: dict, vision: dict) -> Callable[[object], tuple[object, object]]:
    def build(processor):
        import transformers

        tok = processor.tokenizer
        names = {"image": "image_pad", "video": "video_pad", "vision_start": "vision_start", "vision_end": "vision_end"}
        ids = {f"{k}_token_id": tok.convert_tokens_to_ids(f"<|{t}|>") for k, t in names.items()}
        config = getattr(transformers, config_cls_name)(text_config=text, vision_config=vision, **ids)
        model = random_model(config)
        model.generation_config.eos_token_id = tok.convert_tokens_to_ids("<|im_end|>")
        return model, processor

    return build


def build_smolvlm(processor):
    from transformers import Idefics3Config

    tok = processor.tokenizer
    config = Idefics3Config(
        text_config=SMOLVLM_256M_TEXT,
        vision_config=SMOLVLM_256M_VISION,
        scale_factor=4,
        image_token_id=tok.convert_tokens_to_ids("<image>"),
        tie_word_embeddings=False,
    )
    model = random_model(config)
    model.generation_config.eos_token_id = tok.convert_tokens_to_ids("<end_of_utterance>")
    return model, processor


FAMILIES = {
    f.name: f
    for f in (
        Family(
            "qwen2-vl-2b",
            "Qwen/Qwen2-VL-2B-Instruct",
            build_qwen("Qwen2VLConfig", QWEN2VL_2B_TEXT, QWEN2VL_2B_VISION),
            qwen_processor("Qwen2VLProcessor"),
            "<|image_pad|>",
            QWEN2VL_2B_TEXT["max_position_embeddings"],
        ),
        Family(
            "qwen2.5-vl-3b",
            "Qwen/Qwen2.5-VL-3B-Instruct",
            build_qwen("Qwen2_5_VLConfig", QWEN25VL_3B_TEXT, QWEN25VL_3B_VISION),
            qwen_processor("Qwen2_5_VLProcessor"),
            "<|image_pad|>",
            QWEN25VL_3B_TEXT["max_position_embeddings"],
        ),
        Family(
            "smolvlm-256m",
            "HuggingFaceTB/SmolVLM-256M-Instruct",
            build_smolvlm,
            smolvlm_processor,
            "<image>",
            SMOLVLM_256M_TEXT["max_position_embeddings"],
        ),
    )
}


def backend_for(family: Family, processor_dir: Path | None):
    """HFBackend around the random full-size model, given the model and processor instead of loading them."""
    from vlmproprio.backends.hf import HFBackend, load_processor
    from vlmproprio.backends.tiny import ensure_tiny_model

    if processor_dir is not None:
        processor, via = load_processor(processor_dir)
    else:
        processor = family.processor()
        via = f"{type(processor).__name__}, tiny tokenizer"
    model, processor = family.build(processor)
    processor.tokenizer.padding_side = "left"
    if processor.tokenizer.pad_token_id is None:
        processor.tokenizer.pad_token = processor.tokenizer.eos_token
    model.generation_config.pad_token_id = processor.tokenizer.pad_token_id
    # any local folder serves as the weights' name: the model itself is handed over below
    backend = HFBackend(ensure_tiny_model("qwen2-vl"), model_id=f"{family.checkpoint} architecture, random weights")
    backend.weights = dataclasses.replace(backend.weights, revision="random (seed 0)", source="memory")
    backend.dtype = "bfloat16"
    backend.model, backend.processor, backend.processor_via = model, processor, via
    return backend


# ---------------------------------------------------------------------------------------------- requests


def episode_requests(episode: str, condition: str) -> dict[str, list]:
    """The requests of one episode under one condition, by stage, made by the pipeline (as ``pipeline_waves``)."""
    from vlmproprio.backends.reference import ReferenceBackend
    from vlmproprio.chat import GenerationConfig
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.pipeline import PipelineSettings, caption_episodes

    episodes = [e for e in load_episodes(FIXTURES) if e.episode_id == episode]
    if not episodes:
        raise SystemExit(f"no fixture episode {episode!r} in {FIXTURES}")
    settings = PipelineSettings(generation=GenerationConfig(max_new_tokens=1))
    reference = ReferenceBackend()
    by_stage: dict[str, list] = {"p1": [], "p2": [], "p3": []}

    def answer(requests):
        for r in requests:
            by_stage[r.tag.stage].append(r)
        return reference.generate(requests)

    caption_episodes(episodes, parse_conditions(condition), answer, "reference", settings, chunk=10**9, progress=False)
    return by_stage


# ---------------------------------------------------------------------------------------------- measuring


def rss_gb(field: str) -> float:
    """VmRSS or VmHWM of this process, GB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024 / 1e9
    raise RuntimeError(f"no {field} in /proc/self/status")


def token_counts(backend, request, image_token: str) -> tuple[int, int]:
    """Prompt tokens and image tokens of one request, from the family's processor (no model)."""
    from vlmproprio.backends.hf import _decode_image

    images = [_decode_image(img, request) for img in request.images]
    inputs = backend.processor(
        images=images or None, text=[backend._chat_text(request)], padding=True, return_tensors="pt"
    )
    ids = inputs["input_ids"][0]
    return int(ids.numel()), int((ids == backend.processor.tokenizer.convert_tokens_to_ids(image_token)).sum())


def measure(backend, family: Family, stage: str, request, forward: bool) -> dict:
    prompt, image = token_counts(backend, request, family.image_token)
    row = {
        "family": family.name,
        "request": f"{stage.upper()} ({len(request.images)} frames)",
        "prompt_tokens": prompt,
        "image_tokens_per_frame": image / max(len(request.images), 1),
        "context": f"{prompt} / {family.context} ({100 * prompt / family.context:.0f} %)",
        "fits": prompt < family.context,
    }
    if not forward:
        return {**row, "forward": "skipped (--tokens-only)"}
    gc.collect()
    Path("/proc/self/clear_refs").write_text("5")  # VmHWM back to the current RSS (Linux)
    t0 = time.perf_counter()
    (answer,) = backend.generate([request])
    wall = time.perf_counter() - t0
    if answer.meta.prompt_tokens != prompt:
        raise RuntimeError(f"{family.name}: backend saw {answer.meta.prompt_tokens} prompt tokens, processor {prompt}")
    return {**row, "forward": "prefill + 1 token", "wall_s": wall, "peak_rss_gb": rss_gb("VmHWM")}


def run_family(family: Family, requests: dict, processor_dir: Path | None, tokens_only: bool) -> list[dict]:
    t0 = time.perf_counter()
    backend = backend_for(family, processor_dir)
    build_s = time.perf_counter() - t0
    total, _ = weight_bytes(backend.model)
    params = sum(p.numel() for p in backend.model.parameters())
    info = {"weights_gb": total / 1e9, "params_b": params / 1e9, "build_s": build_s, "rss_loaded_gb": rss_gb("VmRSS")}
    emit({"what": "model", "family": family.name, **info})
    rows = []
    for stage, request in requests.items():
        forward = not (tokens_only and stage == "p3")
        rows.append({**measure(backend, family, stage, request, forward), **info})
        emit({"what": "request", **rows[-1]})
    backend.close()
    gc.collect()
    return rows


def pick(by_stage: dict[str, list]) -> dict:
    """The first Process-1 request with the most frames (5) and the Process-3 request with the most (the cap)."""
    return {stage: max(by_stage[stage], key=lambda r: len(r.images)) for stage in ("p1", "p3")}


def processor_dirs(pairs: list[str]) -> dict[str, Path]:
    out = {}
    for pair in pairs:
        name, sep, folder = pair.partition("=")
        if not sep or name not in FAMILIES:
            raise SystemExit(f"--processor-dir wants FAMILY=DIR with FAMILY one of {', '.join(FAMILIES)}; got {pair!r}")
        out[name] = Path(folder)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--family", action="append", choices=list(FAMILIES), help="families to run (default all)")
    ap.add_argument("--episode", default="door_00", help="fixture episode (default door_00)")
    ap.add_argument("--condition", default="both", help="condition (default both)")
    ap.add_argument("--tokens-only", action="append", default=[], choices=list(FAMILIES), help="no P3 forward")
    ap.add_argument("--processor-dir", action="append", default=[], help="FAMILY=DIR: a real processor folder")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--out", type=Path, help="also write every number as JSON here")
    args = ap.parse_args(argv)
    dirs = processor_dirs(args.processor_dir)

    import torch

    torch.set_num_threads(args.threads)
    info = {"what": "machine", **machine(), "threads": args.threads, "date": time.strftime("%Y-%m-%d %H:%M UTC")}
    emit(info)
    requests = pick(episode_requests(args.episode, args.condition))
    rows = []
    for name in args.family or list(FAMILIES):
        rows += run_family(FAMILIES[name], requests, dirs.get(name), name in args.tokens_only)
    cols = ["family", "request", "prompt_tokens", "image_tokens_per_frame", "context", "fits", "forward"]
    cols += ["wall_s", "peak_rss_gb", "rss_loaded_gb", "weights_gb", "params_b", "build_s"]
    print()
    print(f"episode {args.episode}, condition {args.condition}; CPU, {args.threads} threads, bf16, max_new_tokens=1")
    print(table(rows, cols))
    real = ", ".join(dirs) or "none"
    print(f"text tokens: the suite's tiny tokenizer (real processor for: {real}); image tokens: exact")
    write_json(args.out, {"machine": info, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
