"""Live captioning throughput of the suite's own hf path, side by side in one run.

    python perf/gpu_throughput.py --out perf/results/gpu_throughput.json   # one GPU (CUDA)
    python perf/gpu_throughput.py --tiny                                         # CPU, tiny model, < 1 min

Model: the full-size Qwen2-VL-2B-Instruct architecture, built from its published
config with random bf16 weights (no weights can be downloaded; throughput does
not depend on their values), or with ``--tiny`` the tiny random Qwen2-VL of the
tests. Its processor is the tiny model's (real Qwen2-VL image geometry: a
256x256 frame is 81 tokens; a small byte-level BPE for text, so text token
counts differ from the real tokenizer's: the script prints the prompt lengths).

Requests: built by the suite itself. ``caption_episodes`` runs over all 22
fixture episodes x 8 conditions; its Process 1 wave is the real P1 prompt with
up to 5 fixture frames of 256x256 per request. Processes 2 and 3 need earlier
answers, which come from the reference captioner (rule-based, not a model), so
their prompts have the shape they would have in a real run. Every request
forces the same number of new tokens (``min_new_tokens = max_new_tokens``),
so the work is comparable whatever the random model writes.

Measured, on one evenly spread sample of the P1 wave (all episodes and conditions):

* ``one-at-a-time``: ``HFBackend`` with ``max_batch_size=1`` and the default
  dynamic cache, i.e. plain ``generate()`` per request;
* ``live b=B``: the suite's live path, the scheduler + static KV cache +
  compiled decode step (compiled on a GPU only), for each batch size B. The
  first pass over the sample pays the compilation and is reported apart; the
  second pass is the steady state;
* decode time per step at the largest batch (``(t(N new) - t(1 new)) / (N-1)``)
  against the weights-read bound (bytes of weights / memory bandwidth);
* the whole benchmark for one model (22 episodes x 8 conditions, all three
  processes): each wave's size divided by the rate measured on a sample of it.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from pathlib import Path

from _common import FIXTURES, emit, machine, table, write_json

# Qwen/Qwen2-VL-2B-Instruct, config.json as published (2.21 B parameters)
QWEN2VL_2B_TEXT = dict(
    vocab_size=151936,
    hidden_size=1536,
    intermediate_size=8960,
    num_hidden_layers=28,
    num_attention_heads=12,
    num_key_value_heads=2,
    max_position_embeddings=32768,
    rms_norm_eps=1e-6,
    hidden_act="silu",
    tie_word_embeddings=True,
    rope_parameters={"rope_type": "default", "rope_theta": 1000000.0, "mrope_section": [16, 24, 24]},
)
QWEN2VL_2B_VISION = dict(
    depth=32,
    embed_dim=1280,
    hidden_size=1536,
    mlp_ratio=4,
    num_heads=16,
    in_chans=3,
    patch_size=14,
    spatial_merge_size=2,
    temporal_patch_size=2,
)


# ---------------------------------------------------------------------------------------------- requests


def pipeline_waves(new_tokens: int) -> dict:
    """Every request of the three waves for 22 episodes x 8 conditions, made by the suite's pipeline."""
    from vlmproprio.backends.reference import ReferenceBackend
    from vlmproprio.chat import GenerationConfig
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.pipeline import PipelineSettings, caption_episodes

    episodes = load_episodes(FIXTURES)
    settings = PipelineSettings(generation=GenerationConfig(max_new_tokens=new_tokens, min_new_tokens=new_tokens))
    reference = ReferenceBackend()
    waves: dict = {"p1": [], "p2": [], "p3": []}

    def answer(requests):
        for r in requests:
            waves[r.tag.stage].append(r)
        return reference.generate(requests)

    caption_episodes(episodes, parse_conditions("all"), answer, "reference", settings, chunk=10**9, progress=False)
    waves["cells"] = len(episodes) * len(parse_conditions("all"))
    return waves


def spread(requests: list, n: int) -> list:
    """``n`` requests evenly spread over the list (every episode and condition is represented)."""
    if n >= len(requests):
        return list(requests)
    return [requests[(i * len(requests)) // n] for i in range(n)]


# ---------------------------------------------------------------------------------------------- models


def tiny_backend(threads: int, processor_dir: Path | None):
    from vlmproprio.backends.hf import HFBackend, load_processor
    from vlmproprio.backends.tiny import ensure_tiny_model

    backend = HFBackend(ensure_tiny_model("qwen2-vl"), model_id="tiny-qwen2-vl", device="cpu", threads=threads)
    backend.load()
    if processor_dir is not None:
        backend.processor, backend.processor_via = load_processor(processor_dir)
        backend.processor.tokenizer.padding_side = "left"
    return backend


def full_size_backend(attn: str, processor_dir: Path | None, shrunk: bool = False):
    """HFBackend around the Qwen2-VL-2B architecture with random bf16 weights, built on the GPU.

    ``shrunk``: the same code on a CPU with the config cut to 2 narrow layers (checks this script without a GPU)."""
    import dataclasses

    import torch
    from transformers import AutoModelForImageTextToText, Qwen2VLConfig

    from vlmproprio.backends.hf import HFBackend, load_processor
    from vlmproprio.backends.tiny import ensure_tiny_model

    device, dtype = ("cpu", "float32") if shrunk else ("cuda", "bfloat16")
    if device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("no CUDA GPU: run with --tiny on a CPU (the full-size model needs a GPU)")
    tiny = ensure_tiny_model("qwen2-vl")
    processor, via = load_processor(processor_dir or tiny)
    tok = processor.tokenizer
    ids = {
        "image_token_id": tok.convert_tokens_to_ids("<|image_pad|>"),
        "video_token_id": tok.convert_tokens_to_ids("<|video_pad|>"),
        "vision_start_token_id": tok.convert_tokens_to_ids("<|vision_start|>"),
        "vision_end_token_id": tok.convert_tokens_to_ids("<|vision_end|>"),
    }
    text, vision = dict(QWEN2VL_2B_TEXT), dict(QWEN2VL_2B_VISION)
    if shrunk:
        text.update(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4)
        text["rope_parameters"] = {**text["rope_parameters"], "mrope_section": [2, 3, 3]}
        vision.update(depth=2, embed_dim=32, hidden_size=64, num_heads=4)
    config = Qwen2VLConfig(text_config=text, vision_config=vision, **ids)
    torch.manual_seed(0)
    with torch.device(device):
        model = AutoModelForImageTextToText.from_config(config, dtype=getattr(torch, dtype), attn_implementation=attn)
    model.eval()
    model.generation_config.eos_token_id = tok.convert_tokens_to_ids("<|im_end|>")
    model.generation_config.pad_token_id = tok.pad_token_id
    # the suite's backend, given the model and processor instead of loading them from a folder
    name = "Qwen2-VL-2B architecture" + (" (shrunk)" if shrunk else "") + ", random weights"
    backend = HFBackend(tiny, model_id=name, dtype=dtype, device=device, attn_implementation=attn)
    backend.weights = dataclasses.replace(backend.weights, revision="random (seed 0)", source="memory")
    tok.padding_side = "left"
    backend.model, backend.processor, backend.processor_via = model, processor, via
    return backend


def variant(base, max_batch_size: int, static_cache: bool):
    """The same loaded model behind other batching settings."""
    b = copy.copy(base)
    b.max_batch_size, b.static_cache = max_batch_size, static_cache
    return b


def weight_bytes(model) -> tuple[int, int]:
    """Bytes of all weights, and of the language model alone (what one decode step reads)."""
    total = sum(p.numel() * p.element_size() for p in model.parameters())
    vision = sum(p.numel() * p.element_size() for n, p in model.named_parameters() if ".visual." in f".{n}")
    return total, total - vision


def kv_bytes_per_token(model) -> int:
    c = model.config.get_text_config(decoder=True)
    head_dim = getattr(c, "head_dim", None) or c.hidden_size // c.num_attention_heads
    return 2 * c.num_hidden_layers * c.num_key_value_heads * head_dim * model.dtype.itemsize


# ---------------------------------------------------------------------------------------------- measuring


def padding_by_window(backend, wave: list, batch_sizes: list[int]) -> list[dict]:
    """Left padding of the whole wave when the scheduler sees chunks of it, as the runner hands them over."""
    from vlmproprio.backends.scheduling import contiguous_batches, padding_stats, plan_batches
    from vlmproprio.pipeline import DEFAULT_CHUNK, answer_chunk

    shapes = backend.request_shapes(wave)

    def planned(size: int, window: int) -> list:
        out = []
        for start in range(0, len(shapes), window):
            part = shapes[start : start + window]
            out += [[start + i for i in b] for b in plan_batches(part, size, backend.max_batch_tokens)]
        return out

    rows = []
    for b in batch_sizes:
        rows.append(
            {
                "batch": b,
                "arrival_order": padding_stats(shapes, contiguous_batches(len(shapes), b)).waste,
                "old_chunks_of_64": padding_stats(shapes, planned(b, DEFAULT_CHUNK)).waste,
                "chunk_now": answer_chunk(b),
                "chunks_now": padding_stats(shapes, planned(b, answer_chunk(b))).waste,
                "whole_wave": padding_stats(shapes, planned(b, len(shapes))).waste,
            }
        )
    return rows


def timed(backend, requests) -> tuple[float, list]:
    t0 = time.perf_counter()
    answers = backend.generate(requests)  # the backend synchronises the GPU after every batch
    return time.perf_counter() - t0, answers


def with_tokens(requests, n: int) -> list:
    import dataclasses

    cfg = dataclasses.replace(requests[0].config, max_new_tokens=n, min_new_tokens=n)
    return [dataclasses.replace(r, config=cfg) for r in requests]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiny", action="store_true", help="tiny random Qwen2-VL on the CPU (tests the script)")
    ap.add_argument(
        "--shrunk", action="store_true", help="the full-size builder with the config cut down, on a CPU (a check)"
    )
    ap.add_argument("--batch-sizes", type=int, nargs="+", help="live batch sizes (default 8 32 64; tiny 2 4 8)")
    ap.add_argument("--new-tokens", type=int, help="forced new tokens per request (default 64; tiny 8)")
    ap.add_argument("--requests", type=int, help="P1 sample for the batched runs (default 256; tiny 16)")
    ap.add_argument("--single", type=int, help="requests run one at a time (default 16; tiny 4)")
    ap.add_argument("--p2-requests", type=int, help="P2 sample for the estimate (default 128; tiny 8)")
    ap.add_argument("--p3-requests", type=int, help="P3 sample for the estimate (default 64; tiny 2)")
    ap.add_argument(
        "--processor", type=Path, help="a real Qwen2-VL processor folder (tokenizer files) instead of the tiny one's"
    )
    ap.add_argument("--no-static-cache", action="store_true", help="live path with the dynamic cache instead")
    ap.add_argument("--attn", default="sdpa", help="attention implementation of the full-size model")
    ap.add_argument("--bandwidth-tbs", type=float, default=3.0, help="memory bandwidth for the bound (TB/s)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads for --tiny")
    ap.add_argument("--out", type=Path, help="also write every number as JSON here")
    args = ap.parse_args(argv)
    tiny = args.tiny or args.shrunk  # both run on a CPU: small samples
    batch_sizes = args.batch_sizes or ([2, 4, 8] if tiny else [8, 32, 64])
    new = args.new_tokens or (8 if tiny else 64)
    n_req = args.requests or (16 if tiny else 256)
    n_single = args.single or (4 if tiny else 16)
    n_est = {"p2": args.p2_requests or (8 if tiny else 128), "p3": args.p3_requests or (2 if tiny else 64)}
    static = not args.no_static_cache

    import torch

    from vlmproprio.backends.scheduling import contiguous_batches, padding_stats

    t0 = time.perf_counter()
    if args.tiny:
        base = tiny_backend(args.threads, args.processor)
    else:
        if args.shrunk:
            torch.set_num_threads(args.threads)
        base = full_size_backend(args.attn, args.processor, shrunk=args.shrunk)
    build_s = time.perf_counter() - t0
    model = base.model
    total_b, lm_b = weight_bytes(model)
    info = {
        "what": "machine",
        **machine(),
        "device": torch.cuda.get_device_name() if model.device.type == "cuda" else "cpu",
        "model": base.weights.model_id,
        "params": sum(p.numel() for p in model.parameters()),
        "dtype": str(model.dtype).removeprefix("torch."),
        "build_s": round(build_s, 1),
        "new_tokens": new,
    }
    emit(info)
    t0 = time.perf_counter()
    waves = pipeline_waves(new)
    p1 = waves["p1"]
    sample = spread(p1, n_req)
    shapes = base.request_shapes(sample)
    req_info = {
        "what": "requests",
        "cells": waves["cells"],
        **{f"{w}_requests": len(waves[w]) for w in ("p1", "p2", "p3")},
        "p1_sample": len(sample),
        "p1_sample_images_mean": round(statistics.mean(s.images for s in shapes), 2),
        "p1_sample_prompt_tokens_mean": round(statistics.mean(s.prompt_tokens for s in shapes)),
        "p1_sample_prompt_tokens_max": max(s.prompt_tokens for s in shapes),
        "build_s": round(time.perf_counter() - t0, 1),
    }
    emit(req_info)
    padding = padding_by_window(base, p1, batch_sizes)
    for row in padding:
        emit({"what": "padding", **row})
    results: list[dict] = []

    # one request at a time, plain generate() with the dynamic cache
    single_at = spread(list(range(len(sample))), n_single)
    single_reqs = [sample[i] for i in single_at]
    one = variant(base, 1, static_cache=False)
    timed(one, single_reqs[:1])  # warm-up (kernels, allocator)
    s, single_answers = timed(one, single_reqs)
    baseline = n_single / s
    results.append(
        {"mode": "one-at-a-time", "batch": 1, "requests": n_single, "s": s, "req_per_s": baseline,
         "new_tok_per_s": n_single * new / s, "speedup": 1.0}
    )  # fmt: skip
    emit({"what": "throughput", **results[-1]})

    # the live path at each batch size
    # compiled shapes are paid for by a first pass; without compilation (a CPU) one pass is the steady state
    compiled = static and model.device.type == "cuda"
    for b in batch_sizes:
        live = variant(base, b, static_cache=static)
        plan = live.plan_batches(sample)
        first_s = timed(live, sample)[0] if compiled else None
        s, answers = timed(live, sample)
        same = sum(a.text == answers[i].text for i, a in zip(single_at, single_answers, strict=True))
        row = {
            "mode": f"live b={b}" + (" static+compile" if compiled else " static" if static else ""),
            "batch": b,
            "requests": len(sample),
            "s": s,
            "first_pass_s": first_s,
            "req_per_s": len(sample) / s,
            "new_tok_per_s": len(sample) * new / s,
            "speedup": len(sample) / s / baseline,
            "padding_waste": padding_stats(shapes, plan).waste,
            "padding_waste_arrival_order": padding_stats(shapes, contiguous_batches(len(sample), b)).waste,
            "same_text_as_one_at_a_time": f"{same}/{len(single_reqs)}",
        }
        results.append(row)
        emit({"what": "throughput", **row})

    # decode time per step at the largest batch size, against the weights-read bound
    b = max(batch_sizes)
    live = variant(base, b, static_cache=static)
    batch = spread(sample, b)
    reps = 2 if compiled else 1
    full_s, answers = min((timed(live, batch) for _ in range(reps)), key=lambda r: r[0])
    prefill_s = min(timed(live, with_tokens(batch, 1))[0] for _ in range(reps))
    step_ms = 1000 * (full_s - prefill_s) / (new - 1)
    extra = answers[0].meta.extra
    cache_len = extra.get("cache_len") or extra["padded_prompt_tokens"] + new  # the dynamic cache grows to this
    bw = args.bandwidth_tbs * 1e12
    decode = {
        "what": "decode step",
        "batch": b,
        "step_ms": step_ms,
        "prefill_s": prefill_s,
        "bound_all_weights_ms": 1000 * total_b / bw,
        "bound_language_model_ms": 1000 * lm_b / bw,
        "bound_lm_plus_kv_ms": 1000 * (lm_b + b * cache_len * kv_bytes_per_token(model)) / bw,
        "weights_gb": total_b / 1e9,
        "language_model_gb": lm_b / 1e9,
        "bandwidth_tbs": args.bandwidth_tbs,
    }
    emit(decode)

    # the whole benchmark for one model: each wave at the largest batch size
    est_rows = []
    best = next(r for r in results if r["batch"] == b and r["mode"] != "one-at-a-time")
    rates = {"p1": best["req_per_s"]}
    for wave in ("p2", "p3"):
        part = spread(waves[wave], n_est[wave])
        first_s = timed(live, part)[0] if compiled else None
        s, _ = timed(live, part)
        rates[wave] = len(part) / s
        est_rows.append({"wave": wave, "sample": len(part), "s": s, "first_pass_s": first_s, "req_per_s": rates[wave]})
    est_rows.insert(0, {"wave": "p1", "sample": best["requests"], "s": best["s"], "req_per_s": rates["p1"]})
    for r in est_rows:
        r["wave_requests"] = len(waves[r["wave"]])
        r["wave_s"] = r["wave_requests"] / r["req_per_s"]
        emit({"what": "wave", **r})
    whole = sum(r["wave_s"] for r in est_rows)
    compile_s = sum(r["first_pass_s"] - r["s"] for r in results[1:] + est_rows[1:] if r.get("first_pass_s"))
    estimate = {
        "what": "whole benchmark estimate",
        "cells": waves["cells"],
        "requests": sum(r["wave_requests"] for r in est_rows),
        "steady_state_s": whole,
        "first_pass_overhead_measured_s": compile_s,
        "one_at_a_time_s": sum(r["wave_requests"] for r in est_rows) / baseline,
    }
    emit(estimate)

    print()
    print(f"device: {info['device']}; model: {info['model']}, {info['params'] / 1e9:.2f} B params, {info['dtype']}")
    print(
        f"requests: P1 sample of {len(sample)} from {len(p1)} (mean {req_info['p1_sample_prompt_tokens_mean']} prompt "
        f"tokens, {req_info['p1_sample_images_mean']} images); {new} new tokens forced per request"
    )
    print()
    cols = ["mode", "batch", "requests", "s", "first_pass_s", "req_per_s", "new_tok_per_s", "speedup"]
    cols += ["padding_waste", "padding_waste_arrival_order", "same_text_as_one_at_a_time"]
    print(table(results, cols))
    print()
    print(f"left padding over the whole P1 wave ({len(p1)} requests), fraction of prefill positions:")
    print(table(padding, ["batch", "arrival_order", "old_chunks_of_64", "chunks_now", "chunk_now", "whole_wave"]))
    print()
    print(
        table([decode], ["batch", "step_ms", "bound_all_weights_ms", "bound_language_model_ms", "bound_lm_plus_kv_ms"])
    )
    print()
    print(table(est_rows, ["wave", "sample", "req_per_s", "wave_requests", "wave_s"]))
    print(
        f"\nwhole benchmark, one model ({waves['cells']} cells, {estimate['requests']} requests): "
        f"{whole:.0f} s steady state (+ {compile_s:.0f} s of first passes measured here); "
        f"one at a time: {estimate['one_at_a_time_s']:.0f} s"
    )
    write_json(
        args.out,
        {"machine": info, "requests": req_info, "padding": padding, "throughput": results, "decode": decode,
         "waves": est_rows, "estimate": estimate},
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
