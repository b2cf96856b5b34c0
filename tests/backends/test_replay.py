"""Replay needs no model library: a cassette is enough."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_replay_imports_no_model_library(tmp_path):
    code = textwrap.dedent(
        f"""
        import sys
        from vlmproprio.backends.registry import BackendSettings, create_backend
        from vlmproprio.cache import CacheEntry, request_key
        from vlmproprio.cassettes import write_cassette
        from vlmproprio.answering import Answerer
        from vlmproprio.chat import ChatRequest, Message, TextPart
        ident = {{"backend": "hf", "model_id": "Qwen/Qwen2-VL-2B-Instruct", "revision": "abc", "dtype": "bfloat16",
                 "attn_implementation": "sdpa"}}
        req = ChatRequest(messages=(Message("user", (TextPart("# Process 3\\nhi"),)),))
        key = request_key(ident, req)
        entry = CacheEntry(key=key, text="Open the door.", meta={{"backend": "hf", "model_id": "Qwen/Qwen2-VL-2B-Instruct"}}, tag={{}})
        write_cassette(r"{tmp_path}/qwen2-vl.jsonl", "qwen2-vl", ident, [entry])
        backend = create_backend("qwen2-vl", "replay", BackendSettings(cassette_dir=r"{tmp_path}"))
        (answer,) = Answerer(backend, mode="replay").answer([req])
        assert answer.text == "Open the door." and answer.from_cache
        heavy = sorted(m for m in ("torch", "transformers", "openai", "huggingface_hub") if m in sys.modules)
        print("heavy:", heavy)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "heavy: []"
