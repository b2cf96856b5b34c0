"""The hf backend's scheduler and static KV cache on the tiny random Qwen2-VL (CPU)."""

from __future__ import annotations

import importlib.util

import pytest

from vlmproprio.answering import Answerer
from vlmproprio.backends.base import BackendError
from vlmproprio.chat import GenerationConfig, RequestTag
from vlmproprio.conditions import CONDITIONS

# checked, not imported: every xdist worker collects this module, and only the one that runs it needs transformers
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("transformers") is None,
    reason="the hf backend needs transformers (pip install 'vlmproprio[hf]')",
)

STATE = "Frame {n}: joint angles [0.012, 0.301, -0.015, -2.310, 0.010, 2.614, 0.785, 0.080]\n"


def mixed_shapes(request_factory, png_factory, n: int = 9, new: int = 10):
    """Requests with 5 images, 1 image and no image, in turn, and one or two state lines. A 256x256 frame is
    81 tokens, more than a state line, so the image count orders them."""
    out = []
    for i in range(n):
        k = (5, 1, 0)[i % 3]
        text = f"# Process 1, group {i}\nDescribe each frame.\n" + "".join(
            STATE.format(n=j + 1) for j in range(1 + i % 2)
        )
        images = tuple(png_factory(100 + 7 * i + j, 256) for j in range(k))
        config = GenerationConfig(max_new_tokens=new)
        out.append(request_factory(text, images, config=config, tag=RequestTag("door_00", "both", "p1", i)))
    return out


@pytest.fixture
def make_backend(tiny_qwen2vl_dir):
    from vlmproprio.backends.hf import HFBackend

    def make(**kw):
        kw.setdefault("threads", 1)
        return HFBackend(tiny_qwen2vl_dir, model_id="tiny-qwen2-vl", **kw)

    return make


def test_scheduled_batches_equal_one_by_one(make_backend, request_factory, png_factory):
    reqs = mixed_shapes(request_factory, png_factory)
    backend = make_backend(max_batch_size=3)
    plan = backend.plan_batches(reqs)
    assert sorted(i for b in plan for i in b) == list(range(len(reqs)))
    assert plan != [(0, 1, 2), (3, 4, 5), (6, 7, 8)]  # arrival order mixes 5, 1 and 0 images in every batch
    assert [len({len(reqs[i].images) for i in b}) for b in plan] == [1, 1, 1]  # the plan does not
    batched = backend.generate(reqs)
    single = [backend.generate([r])[0] for r in reqs]
    assert [a.text for a in batched] == [a.text for a in single]
    assert [a.meta.completion_tokens for a in batched] == [a.meta.completion_tokens for a in single]
    assert [a.meta.prompt_tokens for a in batched] == [a.meta.prompt_tokens for a in single]
    assert len({a.text for a in single}) > 1  # answers depend on the input, so equality means something
    assert {a.meta.extra["batch_size"] for a in batched} == {3}
    assert {a.meta.extra["kv_cache"] for a in batched} == {"dynamic"}


def test_request_shapes_count_the_tokens_the_processor_makes(make_backend, request_factory, png_factory):
    reqs = mixed_shapes(request_factory, png_factory, n=6)
    reqs.append(request_factory("# Process 1\nhi", (png_factory(1, 256),)))  # 81 image tokens
    backend = make_backend()
    shapes = backend.request_shapes(reqs)
    answered = [backend.generate([r])[0] for r in reqs]
    assert [s.prompt_tokens for s in shapes] == [a.meta.prompt_tokens for a in answered]
    assert [s.images for s in shapes] == [len(r.images) for r in reqs]


def test_cached_backend_hands_the_backend_its_own_plan(make_backend, request_factory, png_factory):
    reqs = mixed_shapes(request_factory, png_factory)
    backend = make_backend(max_batch_size=3)
    seen = []
    generate = backend.generate
    backend.generate = lambda batch: seen.append([len(r.images) for r in batch]) or generate(batch)
    answers = Answerer(backend, mode="live", cache=None).answer(reqs)
    assert [sorted(s) for s in seen] == [[5, 5, 5], [1, 1, 1], [0, 0, 0]]
    assert [a.text for a in answers] == [a.text for a in make_backend(max_batch_size=1).generate(reqs)]


def test_static_cache_gives_the_same_answers(make_backend, request_factory, png_factory):
    reqs = mixed_shapes(request_factory, png_factory, n=6, new=12)
    dynamic = make_backend(max_batch_size=3).generate(reqs)
    static = make_backend(max_batch_size=3, static_cache=True, cache_bucket=64).generate(reqs)
    assert [a.text for a in static] == [a.text for a in dynamic]
    for a in static:
        extra = a.meta.extra
        assert extra["kv_cache"] == "static" and extra["compiled_decode"] is False  # no compilation on a CPU
        assert extra["cache_len"] % 64 == 0 and extra["cache_len"] >= extra["padded_prompt_tokens"] + 12


def test_a_static_cache_is_reused_for_the_next_batch_of_its_shape(make_backend, request_factory, png_factory):
    reqs = mixed_shapes(request_factory, png_factory, n=3, new=12)
    backend = make_backend(max_batch_size=3, static_cache=True)
    first = backend.generate(reqs)
    cache = backend._static[1]
    assert [a.text for a in backend.generate(reqs)] == [a.text for a in first]  # reset between uses
    assert backend._static[1] is cache
    backend.generate(reqs[:2])  # another batch size: another cache, the old one let go
    assert backend._static[1] is not cache and backend._static[0][0] == 2


@pytest.mark.slow
def test_compiled_decode_step_runs_on_cpu(make_backend, request_factory, png_factory):
    """torch.compile of the decode step, forced on a CPU (transformers compiles on GPUs only); ~30 s."""
    import torch

    reqs = mixed_shapes(request_factory, png_factory, n=3, new=8)
    dynamic = make_backend(max_batch_size=3).generate(reqs)
    backend = make_backend(max_batch_size=3, static_cache=True, compile_decode=True)
    torch._dynamo.reset()
    before = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    compiled = backend.generate(reqs)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] > before  # something was really compiled
    assert [a.text for a in compiled] == [a.text for a in dynamic]
    assert all(a.meta.extra["compiled_decode"] is True for a in compiled)
    assert [a.text for a in backend.generate(reqs)] == [a.text for a in dynamic]  # second call: compiled graph


def test_static_cache_setting_reaches_the_backend(vlmproprio_home, torch_one_thread, make_backend):
    from vlmproprio.backends.registry import BackendSettings, create_backend
    from vlmproprio.cli import build_parser

    args = build_parser().parse_args(["run", "--model", "tiny-qwen2-vl", "--static-cache", "--batch-size", "32"])
    assert args.static_cache is True
    assert build_parser().parse_args(["run", "--model", "tiny-qwen2-vl"]).static_cache is False
    backend = create_backend("tiny-qwen2-vl", "live", BackendSettings.of(static_cache=True, max_batch_size=32))
    assert (backend.static_cache, backend.compile_decode, backend.max_batch_size) == (True, None, 32)
    assert create_backend("tiny-qwen2-vl", "live").static_cache is False
    args = build_parser().parse_args(["run", "--model", "tiny-qwen2-vl", "--batch-tokens", "4096"])
    assert args.batch_tokens == 4096
    backend = create_backend("tiny-qwen2-vl", "live", BackendSettings.of(max_batch_tokens=4096))
    assert backend.max_batch_tokens == 4096
    with pytest.raises(BackendError, match="needs the static KV cache"):
        make_backend(compile_decode=True)
    with pytest.raises(BackendError, match="cache_bucket"):
        make_backend(static_cache=True, cache_bucket=0)
    with pytest.raises(BackendError, match="max_batch_tokens"):
        make_backend(max_batch_tokens=0)


def test_a_cpu_batch_is_capped_in_tokens(make_backend, request_factory, png_factory):
    from vlmproprio.backends.hf import CPU_BATCH_TOKENS

    reqs = mixed_shapes(request_factory, png_factory, n=6)
    assert make_backend().max_batch_tokens == CPU_BATCH_TOKENS  # the default on a CPU
    shapes = make_backend().request_shapes(reqs)
    budget = max(s.prompt_tokens for s in shapes) + 1  # room for one row of the longest prompt, not two
    backend = make_backend(max_batch_size=6, max_batch_tokens=budget)
    plan = backend.plan_batches(reqs)
    assert all(len(b) * max(shapes[i].prompt_tokens for i in b) <= budget or len(b) == 1 for b in plan)
    assert len(plan[0]) == 1 and len(plan) > 1
    assert [a.text for a in backend.generate(reqs)] == [a.text for a in make_backend(max_batch_size=1).generate(reqs)]


def test_identity_ignores_how_answers_are_computed(make_backend):
    # static cache and batch size change how, not what: like the device they stay out of the cache key
    assert make_backend(static_cache=True, max_batch_size=64).identity() == make_backend().identity()


def run_perf_script(name: str, argv: list[str], monkeypatch) -> int:
    """``perf/<name>.py``'s ``main(argv)`` in this process: torch and transformers are loaded here already (a
    subprocess spent ~6 s of CPU importing them again), and what is tested is the script's code, not its process.
    perf/ goes on sys.path for the script's ``from _common import ...``; sys.path is restored afterwards."""
    import importlib.util
    import sys
    from pathlib import Path

    perf = Path(__file__).resolve().parents[2] / "perf"
    monkeypatch.syspath_prepend(str(perf))
    monkeypatch.setitem(sys.modules, "_common", None)  # recorded, so the import below is undone afterwards
    del sys.modules["_common"]
    spec = importlib.util.spec_from_file_location(f"perf_{name}", perf / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main(argv)


@pytest.mark.slow
def test_the_throughput_benchmark_runs_on_the_tiny_model(tmp_path, tiny_qwen2vl_dir, monkeypatch):
    """perf/gpu_throughput.py --tiny, cut down: the GPU benchmark's code path must not rot untested."""
    import json

    from vlmproprio.backends.tiny import tiny_model_dir

    assert tiny_qwen2vl_dir == tiny_model_dir("qwen2-vl")  # the script's ensure_tiny_model finds the session's
    out = tmp_path / "t.json"
    argv = ["--tiny", "--out", str(out), "--requests", "4", "--single", "2", "--batch-sizes", "2", "4"]
    argv += ["--new-tokens", "4", "--p2-requests", "2", "--p3-requests", "1"]
    assert run_perf_script("gpu_throughput", argv, monkeypatch) == 0
    doc = json.loads(out.read_text())
    rows = doc["throughput"]
    assert [r["mode"] for r in rows] == ["one-at-a-time", "live b=2 static", "live b=4 static"]
    assert all(r["req_per_s"] > 0 for r in rows)
    assert {r["same_text_as_one_at_a_time"] for r in rows[1:]} == {"2/2"}  # batching changed no answer
    cells = 22 * len(CONDITIONS)  # every episode under every condition
    groups = 136 * len(CONDITIONS)  # 136 groups of k = 5 frames over the 22 episodes, per condition
    assert doc["requests"]["p1_requests"] == groups and doc["requests"]["cells"] == cells
    assert [w["wave"] for w in doc["waves"]] == ["p1", "p2", "p3"]
    assert doc["estimate"]["requests"] == groups + groups + cells


def pipeline_prompts(episode_ids: tuple[str, ...]) -> list:
    """Every request (Processes 1-3) the pipeline makes for these episodes under every condition."""
    from pathlib import Path

    from vlmproprio.backends.reference import ReferenceBackend
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.pipeline import caption_episodes

    fixtures = Path(__file__).resolve().parents[2] / "fixtures"
    reference, seen = ReferenceBackend(), []

    def answer(requests):
        seen.extend(requests)
        return reference.generate(requests)

    episodes = load_episodes(fixtures, episode_ids)
    caption_episodes(episodes, parse_conditions("all"), answer, "reference", chunk=10**9, progress=False)
    return seen


def test_prompt_lengths_counted_by_pieces_equal_whole_texts(tiny_qwen2vl_backend):
    """The scheduler counts a prompt's tokens piece by piece between added tokens, with the pieces cached
    (hf_tokens): the counts must be those of tokenizing each whole text, on the pipeline's real prompts (one
    episode, every condition, Processes 1-3: every template part and kind of state text)."""
    from vlmproprio.backends.hf_tokens import PromptTokenCounter

    backend = tiny_qwen2vl_backend
    requests = pipeline_prompts(("door_02",))
    texts = [backend._chat_text(r) for r in requests]
    tok = backend.processor.tokenizer
    whole = [len(ids) for ids in tok(texts, add_special_tokens=False)["input_ids"]]
    counter = PromptTokenCounter(tok)
    assert counter.pattern is not None  # the pieces path, not the whole-text fallback
    assert {r.tag.stage for r in requests} == {"p1", "p2", "p3"} and len(set(whole)) > 10
    assert counter.counts(texts) == whole
    assert counter.counts(texts[::-1]) == whole[::-1]  # from the cache
    images = [sum(backend._tokens_of(i) - 1 for i in r.images) for r in requests]
    assert [s.prompt_tokens for s in backend.request_shapes(requests)] == [
        w + n for w, n in zip(whole, images, strict=True)
    ]


def test_prompt_lengths_fall_back_to_whole_texts(tiny_qwen2vl_backend):
    """An added token that is normalized or strips whitespace is not matched on the raw text: no cutting."""
    from tokenizers import AddedToken

    from vlmproprio.backends.hf_tokens import PromptTokenCounter, added_token_pattern

    tok = tiny_qwen2vl_backend.processor.tokenizer
    assert added_token_pattern(tok) is not None
    other = type(tok).from_pretrained(tiny_qwen2vl_backend.weights.path)
    other.add_tokens([AddedToken("<|joint|>", lstrip=True)])
    assert added_token_pattern(other) is None
    text = "Frame 1:  <|joint|> 0.25<|im_end|>\n"
    assert PromptTokenCounter(other).counts([text]) == [len(other(text, add_special_tokens=False)["input_ids"])]


def _metaspace_first_tokenizer():
    """A Llama-2-style tokenizer in miniature: Metaspace prepending '▁' to the first piece of a text only, and a
    vocabulary where 'hello' is one token but '▁hello' two, so a piece tokenized alone counts one more."""
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    vocab = {"[UNK]": 0, "▁": 1, "h": 2, "e": 3, "l": 4, "o": 5, "he": 6, "ll": 7, "hell": 8, "hello": 9}
    merges = [("h", "e"), ("l", "l"), ("he", "ll"), ("hell", "o")]
    raw = Tokenizer(models.BPE(vocab, merges, unk_token="[UNK]"))
    raw.pre_tokenizer = pre_tokenizers.Metaspace(replacement="▁", prepend_scheme="first")
    tok = PreTrainedTokenizerFast(tokenizer_object=raw, unk_token="[UNK]")
    tok.add_special_tokens({"additional_special_tokens": ["<image>"]})
    return tok


def test_prompt_lengths_of_first_piece_prepending_tokenizers_are_counted_whole():
    """'<image>hello' is '<image>', 'hello' whole but '<image>', '▁', 'hello' cut: such tokenizers are not cut, and
    a counter that would cut one anyway (a tokenizer the structural checks miss) finds out on its first texts."""
    import re

    from vlmproprio.backends.hf_tokens import PromptTokenCounter, added_token_pattern

    tok = _metaspace_first_tokenizer()
    texts = ["hello<image>hello", "<image>hello hello"]
    whole = [len(ids) for ids in tok(texts, add_special_tokens=False)["input_ids"]]
    assert whole == [4, 4]
    assert added_token_pattern(tok) is None
    assert PromptTokenCounter(tok).counts(texts) == whole
    forced = PromptTokenCounter(tok)
    forced.pattern = re.compile("(<image>)")  # as if the structural checks had passed
    assert forced._by_pieces(texts) == [5, 5]  # what cutting would have counted
    assert forced.counts(texts) == whole and forced.pattern is None
    assert forced.counts(["<image>hello"]) == [2]
