"""The backends' command-line options: their option groups, and the one table from options to backend settings."""

from __future__ import annotations

import argparse

# command-line option (argparse dest) -> backend setting: the one place the two vocabularies meet
SETTING_OPTIONS = {
    "device": "device",
    "dtype": "dtype",
    "attn": "attn_implementation",
    "batch_size": "max_batch_size",
    "threads": "threads",
    "judge_threads": "threads",
    "static_cache": "static_cache",
    "batch_tokens": "max_batch_tokens",
    "allow_download": "allow_download",
    "base_url": "base_url",
    "api_key_env": "api_key_env",
    "concurrency": "concurrency",
    "timeout": "timeout_s",
}


def backend_settings(args: argparse.Namespace, **paths):
    """The backend settings a command's options give (those it has), plus ``paths`` (cassette_dir, home)."""
    from vlmproprio.backends.settings import BackendSettings

    given = {setting: getattr(args, dest) for dest, setting in SETTING_OPTIONS.items() if hasattr(args, dest)}
    return BackendSettings.of(**given, **paths)


def add_backend_options(p: argparse.ArgumentParser) -> None:
    """run: the option groups of the backend kinds, after the method's."""
    add_hf_options(p.add_argument_group("local models (hf)"))
    g = p.add_argument_group("OpenAI-compatible servers (openai)")
    add_server(g, "server URL, e.g. http://127.0.0.1:8000/v1 for vLLM (default: OpenAI)")
    g.add_argument("--concurrency", type=int, default=4, help="requests in flight (default 4)")
    g.add_argument("--timeout", type=float, default=120.0, help="seconds per request (default 120)")


def add_hf_options(g) -> None:
    """run: how a local (hf:) model is loaded and batched."""
    g.add_argument(
        "--allow-download",
        action="store_true",
        help="fetch missing hf: weights from the Hugging Face Hub when it is reachable (default: local files only)",
    )
    g.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N | auto (default cpu)")
    g.add_argument("--dtype", default="auto", help="auto | float32 | bfloat16 | float16 (default auto)")
    g.add_argument("--attn", default="sdpa", help="attention implementation: eager | sdpa | flash_attention_2")
    g.add_argument("--batch-size", type=int, default=8, help="requests per generate() call (default 8)")
    g.add_argument("--threads", type=int, help="torch threads (pin to 1 for bit-identical CPU runs)")
    g.add_argument(
        "--batch-tokens",
        type=int,
        help="cap on a batch's rows x longest prompt, in tokens (default: 16384 on a CPU, none on a GPU)",
    )
    g.add_argument(
        "--static-cache",
        action="store_true",
        help="static KV cache; on a GPU the decode step is compiled (first batches pay ~1 min; pays on long runs)",
    )


def add_server(g, base_url_help: str) -> None:
    """Where an openai: model is served (run, models, score --judge)."""
    g.add_argument("--base-url", help=base_url_help)
    g.add_argument("--api-key-env", default="OPENAI_API_KEY", help="environment variable holding the key")
