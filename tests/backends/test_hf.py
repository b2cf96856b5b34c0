"""The transformers backend on tiny random checkpoints (real architectures, real processors, CPU)."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
import threading
from dataclasses import replace

import pytest

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import BackendError
from vlmproprio.backends.tiny import file_hashes
from vlmproprio.cache import ResponseCache
from vlmproprio.chat import GenerationConfig, RequestTag

# checked, not imported: every xdist worker collects this module, and only the one that runs it needs transformers
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("transformers") is None,
    reason="the hf backend needs transformers (pip install 'vlmproprio[hf]')",
)

P1_TEXT = (
    "# Process 1\nDescribe what the robot does in each frame, one line per frame.\n"
    "Frame 1: joint angles [0.012, 0.301, -0.015, -2.310, 0.010, 2.614, 0.785, 0.080]; "
    "end-effector [0.102, -0.003, 1.012, 3.139, 0.005, 1.571]"
)


def mixed_requests(request_factory, png_factory, n: int = 4):
    """Requests of different lengths and image counts, so a batch needs real (left) padding."""
    return [
        request_factory(
            P1_TEXT + " extra words" * (3 * i),
            tuple(png_factory(10 * i + j) for j in range(1 + i % 3)),
            config=GenerationConfig(max_new_tokens=12),
            tag=RequestTag("door_00", "both", "p1", i),
        )
        for i in range(n)
    ]


def test_tiny_build_is_sha256_identical_across_builds(tiny_qwen2vl_dir, tmp_path):
    # a second build in a fresh process, through the CLI
    out = tmp_path / "again"
    subprocess.run(
        [sys.executable, "-m", "vlmproprio.cli", "make-tiny-model", "--family", "qwen2-vl", "--out", str(out)],
        check=True,
        capture_output=True,
    )
    first, second = file_hashes(tiny_qwen2vl_dir), file_hashes(out)
    assert "model.safetensors" in first and "tokenizer.json" in first and "chat_template.jinja" in first
    assert first == second


def test_identity_and_revision(tiny_qwen2vl_backend, tiny_qwen2vl_dir):
    from vlmproprio.backends.hf import HFBackend
    from vlmproprio.backends.hf_files import folder_revision

    ident = tiny_qwen2vl_backend.identity()
    assert ident == {
        "backend": "hf",
        "model_id": "tiny-qwen2-vl",
        "revision": folder_revision(tiny_qwen2vl_dir),
        "dtype": "float32",
        "attn_implementation": "sdpa",
    }
    assert ident["revision"].startswith("sha256:")
    other = HFBackend(tiny_qwen2vl_dir, attn_implementation="eager", dtype="bfloat16")
    assert other.identity()["model_id"] == tiny_qwen2vl_dir.name  # a folder is named by its last part
    assert (other.identity()["dtype"], other.identity()["attn_implementation"]) == ("bfloat16", "eager")


def test_batched_equals_one_by_one(tiny_qwen2vl_backend, request_factory, png_factory):
    reqs = mixed_requests(request_factory, png_factory)
    backend = tiny_qwen2vl_backend
    backend.max_batch_size = 4
    batched = backend.generate(reqs)
    single = [backend.generate([r])[0] for r in reqs]
    assert [a.text for a in batched] == [a.text for a in single]
    assert [a.meta.completion_tokens for a in batched] == [a.meta.completion_tokens for a in single]
    assert len({a.text for a in single}) > 1  # the answers depend on the input, so equality means something
    assert [a.meta.prompt_tokens for a in batched] == [a.meta.prompt_tokens for a in single]
    assert batched[0].meta.extra["batch_size"] == 4 and single[0].meta.extra["batch_size"] == 1
    meta = batched[0].meta
    assert (meta.device, meta.dtype, meta.attn_implementation) == ("cpu", "float32", "sdpa")


def test_prompt_shape_matches_the_real_model(tiny_qwen2vl_backend, request_factory, png_factory):
    # a 256x256 frame is 252x252 for the processor: 18x18 patches merged 2x2 = 81 image tokens
    backend = tiny_qwen2vl_backend
    one = backend.generate([request_factory("# Process 1\nhi", (png_factory(1, 256),))])[0]
    none = backend.generate([request_factory("# Process 1\nhi", ())])[0]
    assert one.meta.prompt_tokens - none.meta.prompt_tokens == 81 + 2  # + vision start/end tokens


def test_processor_fallback_patches_nothing(tiny_qwen2vl_backend):
    from transformers import Qwen2VLProcessor
    from transformers.utils import is_torchvision_available

    if is_torchvision_available():
        pytest.skip("torchvision is installed: AutoProcessor is used as is")
    assert tiny_qwen2vl_backend.processor_via == "Qwen2VLProcessor without video processor"
    assert "video_processor" in Qwen2VLProcessor.get_attributes()  # the library class is untouched


@pytest.mark.parametrize("family", ["qwen2.5-vl", "llava"])
def test_other_tiny_families(family, tiny_model, request_factory, png_factory):
    from vlmproprio.backends.hf import HFBackend

    # the session's build (test_transformers_serve serves the same LLaVA when it runs in this process)
    backend = HFBackend(tiny_model(family), max_batch_size=3, threads=1)
    reqs = mixed_requests(request_factory, png_factory, 3)
    batched = backend.generate(reqs)
    single = [backend.generate([r])[0] for r in reqs]
    assert [a.text for a in batched] == [a.text for a in single]
    assert all(a.meta.prompt_tokens > 0 for a in batched)


def test_cached_hf_answers(tiny_qwen2vl_backend, request_factory, png_factory, tmp_path):
    reqs = mixed_requests(request_factory, png_factory, 2)
    with ResponseCache(tmp_path / "c") as cache:
        live = Answerer(tiny_qwen2vl_backend, mode="live", cache=cache, model="tiny-qwen2-vl").answer(reqs)
        again = Answerer(tiny_qwen2vl_backend, mode="replay", cache=cache).answer(reqs)
    assert [a.text for a in again] == [a.text for a in live] and all(a.from_cache for a in again)


def test_missing_weights_say_how_to_get_them(tmp_path):
    from vlmproprio.backends.hf import HFBackend

    with pytest.raises(BackendError, match=r"not in the local Hugging Face cache.*hf download Org/NotHere"):
        HFBackend("Org/NotHere")
    with pytest.raises(BackendError, match="does not exist"):
        HFBackend(str(tmp_path / "nothing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(BackendError, match="no weight files"):
        HFBackend(tmp_path / "empty")


def test_hf_cache_snapshot_gives_the_commit_as_revision(tiny_qwen2vl_dir, tmp_path, monkeypatch):
    import huggingface_hub.constants

    from vlmproprio.backends.hf import HFBackend

    commit = "0123456789abcdef0123456789abcdef01234567"
    repo = tmp_path / "hub" / "models--Org--Tiny"
    shutil.copytree(tiny_qwen2vl_dir, repo / "snapshots" / commit)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    by_id = HFBackend("Org/Tiny").identity()
    by_path = HFBackend(repo / "snapshots" / commit).identity()
    assert by_id["revision"] == by_path["revision"] == commit
    assert by_id["model_id"] == by_path["model_id"] == "Org/Tiny"


def test_bad_settings_and_inputs_are_clear_errors(tiny_qwen2vl_backend, tiny_qwen2vl_dir, request_factory):
    from vlmproprio.backends.hf import HFBackend

    with pytest.raises(BackendError, match="unknown device"):
        HFBackend(tiny_qwen2vl_dir, device="tpu")
    with pytest.raises(BackendError, match="unknown attention implementation"):
        HFBackend(tiny_qwen2vl_dir, attn_implementation="magic")
    hot = request_factory("# Process 1\nhi", ())
    hot = replace(hot, config=replace(hot.config, temperature=0.7))
    with pytest.raises(BackendError, match="greedily"):
        tiny_qwen2vl_backend.generate([hot])
    broken = request_factory(
        "# Process 1\nhi", (b"\x89PNG\r\n\x1a\n truncated",), tag=RequestTag("bin1_02", "ee", "p1", 2)
    )
    with pytest.raises(BackendError, match=r"bin1_02.*cannot decode image"):
        tiny_qwen2vl_backend.generate([broken])


def test_a_prompt_past_the_models_context_is_refused_before_generating(
    tiny_qwen2vl_dir, tmp_path, request_factory, png_factory
):
    """The context comes from the model's own config: a copy of the tiny build whose config says 64 positions
    refuses a five-image Process-1 request, naming the request, its tokens, the context and the fix; the real
    build (32,768) answers the same request."""
    import json

    from vlmproprio.backends.hf import HFBackend
    from vlmproprio.backends.hf_context import context_length

    short = tmp_path / "short"
    shutil.copytree(tiny_qwen2vl_dir, short)
    config = json.loads((short / "config.json").read_text())
    config["text_config"]["max_position_embeddings"] = 64
    (short / "config.json").write_text(json.dumps(config))
    request = request_factory(
        P1_TEXT,
        tuple(png_factory(j) for j in range(5)),
        config=GenerationConfig(max_new_tokens=4),
        tag=RequestTag("bin2_01", "both", "p3", -1),
    )
    backend = HFBackend(short, model_id="tiny-short", device="cpu", dtype="float32", threads=1)
    backend.load()
    assert context_length(backend.model.config) == 64
    with pytest.raises(
        BackendError,
        match=r"tiny-short \(qwen2_vl\): p3 of bin2_01 / both is \d+ prompt tokens "
        r"\(5 images\) \+ 4 new, past the model's context of 64 tokens; .*--max-images-p3",
    ):
        backend.generate([request])
    whole = HFBackend(tiny_qwen2vl_dir, model_id="tiny-qwen2-vl", device="cpu", dtype="float32", threads=1)
    whole.load()
    assert context_length(whole.model.config) == 32768
    (answer,) = whole.generate([request])
    assert answer.meta.prompt_tokens > 64


def test_registry_tiny_model_is_built_once_even_when_raced(vlmproprio_home, torch_one_thread):
    from vlmproprio.backends.registry import create_backend
    from vlmproprio.backends.tiny import ensure_tiny_model, tiny_model_dir

    results, errors = [], []

    def build():
        try:
            results.append(ensure_tiny_model("qwen2-vl"))
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=build) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(set(results)) == 1 and results[0] == tiny_model_dir("qwen2-vl")
    models = vlmproprio_home / "models"
    assert [p.name for p in models.iterdir()] == [results[0].name]  # no temporary folders left behind
    backend = create_backend("tiny-qwen2-vl", "live")
    assert backend.identity()["model_id"] == "tiny-qwen2-vl"
    (results[0] / "config.json").write_text("{}")
    with pytest.raises(BackendError, match=r"differ from their build stamp \(config.json\)"):
        ensure_tiny_model("qwen2-vl")


def test_decoding_is_plain_greedy_whatever_the_checkpoint_suggests(
    tiny_qwen2vl_backend, tiny_qwen2vl_dir, tmp_path, request_factory, png_factory
):
    import json

    from vlmproprio.backends.hf import HFBackend

    # real Qwen2-VL checkpoints ship sampling settings and a repetition penalty in generation_config.json
    qwenlike = shutil.copytree(tiny_qwen2vl_dir, tmp_path / "qwenlike")
    gc = json.loads((qwenlike / "generation_config.json").read_text())
    gc.update(do_sample=True, temperature=0.1, top_p=0.001, top_k=1, repetition_penalty=1.3)  # 1.05 in Qwen2-VL
    (qwenlike / "generation_config.json").write_text(json.dumps(gc))
    reqs = [
        request_factory(P1_TEXT * (i + 1), (png_factory(i),), config=GenerationConfig(max_new_tokens=48))
        for i in range(3)
    ]
    plain = [a.text for a in tiny_qwen2vl_backend.generate(reqs)]
    assert [a.text for a in HFBackend(qwenlike, threads=1).generate(reqs)] == plain


def test_the_thinking_switch_reaches_the_chat_template_and_the_key(tiny_qwen2vl_backend, request_factory, png_factory):
    """--thinking off: ``enable_thinking=False`` in the chat template (Qwen3's switch); absent, the template's
    default. The switch is part of the request's cache key only when it is given."""
    from vlmproprio.cache import request_key

    b = tiny_qwen2vl_backend
    b.load()
    switch = "{% if enable_thinking is defined and not enable_thinking %}<think>\n\n</think>\n\n{% endif %}"
    saved = b.processor.chat_template
    b.processor.chat_template = saved + switch
    try:
        plain = request_factory("Describe.", (png_factory(1),))
        off = replace(plain, config=replace(plain.config, thinking=False))
        on = replace(plain, config=replace(plain.config, thinking=True))
        assert b._chat_text(off).endswith("<think>\n\n</think>\n\n")
        assert not b._chat_text(plain).endswith("</think>\n\n") and not b._chat_text(on).endswith("</think>\n\n")
    finally:
        b.processor.chat_template = saved
    ident = b.identity()
    keys = {request_key(ident, r) for r in (plain, off, on)}
    assert len(keys) == 3
    assert "thinking" not in plain.config.to_dict() and off.config.to_dict()["thinking"] is False
