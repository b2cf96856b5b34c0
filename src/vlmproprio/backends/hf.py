"""Open-weights VLMs through transformers (``AutoModelForImageTextToText`` + the model's processor).

Weights (offline unless downloads are allowed) and the processor come from vlmproprio.backends.hf_files.
Decoding is greedy (the paper's temperature 0). dtype, device (``cpu``, ``cuda``, or ``auto`` = accelerate's
device map) and the attention implementation are explicit settings; dtype and attention enter the cache key
because they change the scores.

Batching: ``plan_batches`` groups the requests it is given by shape (prompt
length with image tokens, number of images; see vlmproprio.backends.scheduling)
into batches of ``max_batch_size`` rows and at most ``max_batch_tokens`` padded
tokens (by default capped on a CPU only); ``Answerer`` asks it for the plan of a
whole wave of misses, and ``generate`` uses it too, putting answers back in
request order. Batches are padded on the left, so every row's prompt ends where
generation starts, and batched greedy outputs equal one-by-one outputs (a test
checks it on the tiny model, with mixed image counts). Decoding is plain greedy
whatever the checkpoint's ``generation_config.json`` suggests (no repetition
penalty). All generation goes through ``_generate_batch``.

Static KV cache (``static_cache=True``, off by default): each batch gets a
``StaticCache`` sized to its prompt plus ``max_new_tokens``, rounded up to
``cache_bucket`` tokens so that batches of a wave share a few cache shapes, and
transformers compiles the decode step with ``torch.compile`` (CUDA graphs) when
the model is on a GPU. The first calls pay the compilation (about a minute on
an H100); it pays on long runs of large batches, where a decode step is bound
by reading the weights. ``compile_decode=True`` compiles on a CPU too (slow to
compile; for tests), ``False`` never. Neither the cache kind nor the batch size
enters the cache key: like the device, they are how an answer was computed,
recorded in ``AnswerMeta.extra``.
"""

from __future__ import annotations

import io
import json
import os
import re
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from vlmproprio.backends.base import Availability, Backend, BackendError
from vlmproprio.backends.hf_context import check_context
from vlmproprio.backends.hf_families import missing_library_message, processor_images
from vlmproprio.backends.hf_files import hf_weights_available, load_processor, resolve_weights
from vlmproprio.backends.hf_tokens import PromptTokenCounter
from vlmproprio.backends.scheduling import RequestShape, plan_batches, round_up
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest, ImagePart
from vlmproprio.kinds import KindOption, KindSpec, register_kind
from vlmproprio.models import ModelRef, file_slug

if TYPE_CHECKING:
    from vlmproprio.backends.settings import BackendSettings

DEVICES = ("cpu", "cuda", "auto")
DTYPES = ("auto", "float32", "bfloat16", "float16")
ATTN_IMPLEMENTATIONS = ("eager", "sdpa", "flash_attention_2", "flash_attention_3", "flex_attention")
# Static caches are sized in steps of this many tokens: few shapes, so few recompilations of the decode step.
DEFAULT_CACHE_BUCKET = 256
# Default cap on a CPU batch's rows x longest prompt. On a CPU a padded batch is no faster than its rows one by
# one, and its attention mask grows with rows x length squared: 8 Process 3 prompts of the tiny model (~9k
# tokens each) in one batch peaked at 4.5 GB of memory and took 3x longer than one at a time.
CPU_BATCH_TOKENS = 16384
# Plain greedy decoding. transformers fills every setting left unset from the checkpoint's generation_config.json,
# and real checkpoints ship sampling and penalty settings (Qwen2-VL: repetition_penalty 1.05, top_k 1, ...), so
# every setting that changes the chosen token is set here, to its neutral value.
PURE_GREEDY: dict = dict(
    do_sample=False,
    num_beams=1,
    repetition_penalty=1.0,
    no_repeat_ngram_size=0,
    encoder_repetition_penalty=1.0,
    temperature=1.0,
    top_k=None,
    top_p=1.0,
)


# ---------------------------------------------------------------------------------------------- backend


class HFBackend(Backend):
    """A transformers VLM, loaded on first use."""

    def __init__(
        self,
        weights: str | Path,
        *,
        model_id: str | None = None,
        dtype: str = "auto",
        device: str = "cpu",
        attn_implementation: str = "sdpa",
        max_batch_size: int = 8,
        threads: int | None = None,
        static_cache: bool = False,
        compile_decode: bool | None = None,
        cache_bucket: int = DEFAULT_CACHE_BUCKET,
        max_batch_tokens: int | None = None,
        allow_download: bool = False,
        revision_memo: Path | None = None,
    ) -> None:
        """``static_cache``: a static KV cache per batch; ``compile_decode``: compile the decode step
        (None: on a GPU only, as transformers does; needs the static cache); ``cache_bucket``: static cache
        lengths are multiples of it; ``max_batch_tokens``: cap on rows x longest prompt of a batch (None:
        CPU_BATCH_TOKENS on a CPU, no cap elsewhere); ``revision_memo``: where a folder's revision is remembered."""
        if device not in DEVICES and not re.fullmatch(r"cuda:\d+", device):
            raise BackendError(f"unknown device {device!r}; choose cpu, cuda, cuda:N or auto")
        if dtype not in DTYPES:
            raise BackendError(f"unknown dtype {dtype!r}; choose from {', '.join(DTYPES)}")
        if attn_implementation not in ATTN_IMPLEMENTATIONS:
            raise BackendError(
                f"unknown attention implementation {attn_implementation!r}; choose from {', '.join(ATTN_IMPLEMENTATIONS)}"
            )
        if max_batch_size < 1:
            raise BackendError(f"max_batch_size must be >= 1, got {max_batch_size}")
        if compile_decode and not static_cache:
            raise BackendError("compiling the decode step needs the static KV cache (static_cache=True)")
        if cache_bucket < 1:
            raise BackendError(f"cache_bucket must be >= 1, got {cache_bucket}")
        if max_batch_tokens is not None and max_batch_tokens < 1:
            raise BackendError(f"max_batch_tokens must be >= 1, got {max_batch_tokens}")
        self.weights = resolve_weights(weights, model_id, allow_download=allow_download, memo=revision_memo)
        self.allow_download = allow_download
        self.device = device
        self.dtype = _resolve_dtype(dtype, device)
        self.attn_implementation = attn_implementation
        self.max_batch_size = max_batch_size
        self.threads = threads
        self.static_cache = static_cache
        self.compile_decode = compile_decode
        self.cache_bucket = cache_bucket
        self.max_batch_tokens = max_batch_tokens if max_batch_tokens or device != "cpu" else CPU_BATCH_TOKENS
        self._image_sizes: dict[str, tuple[int, int] | None] = {}  # image sha256 -> (height, width), for the scheduler
        self._size_tokens: dict[tuple[int, int], int] = {}  # (height, width) -> tokens an image of it becomes
        self._prompt_tokens: PromptTokenCounter | None = None  # prompt lengths for the scheduler (see hf_tokens)
        # the last static cache, kept for the next batch of the same shape: a compiled decode step replays its
        # CUDA graph only while the cache tensors stay at the same addresses
        self._static: tuple[tuple[int, int], object] | None = None
        self.model = None
        self.processor = None
        self.processor_via = ""

    def identity(self) -> dict[str, str]:
        return {
            "backend": "hf",
            "model_id": self.weights.model_id,
            "revision": self.weights.revision,
            "dtype": self.dtype,
            "attn_implementation": self.attn_implementation,
        }

    # -------------------------------------------------------------------------------- loading
    def load(self) -> None:
        if self.model is not None:
            return
        if not self.allow_download:  # local files only, unless the user allowed the Hub
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
        import torch
        from transformers import AutoModelForImageTextToText

        if self.threads:
            torch.set_num_threads(self.threads)
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise BackendError(f"device {self.device!r} asked for, but torch sees no CUDA GPU; use --device cpu")
        path = self.weights.path
        try:
            self.processor, self.processor_via = load_processor(path)
            kwargs = dict(
                dtype=getattr(torch, self.dtype), attn_implementation=self.attn_implementation, local_files_only=True
            )
            if self.device == "auto":
                kwargs["device_map"] = "auto"  # accelerate spreads the layers over what is there
            model = AutoModelForImageTextToText.from_pretrained(path, **kwargs)
        except ImportError as exc:
            raise BackendError(missing_library_message(self.weights.model_id, path, exc)) from exc
        except (OSError, ValueError) as exc:
            raise BackendError(f"cannot load {self.weights.model_id} from {path}: {type(exc).__name__}: {exc}") from exc
        if self.device != "auto":
            model = model.to(self.device)
        self.model = model.eval()
        tok = self.processor.tokenizer
        tok.padding_side = "left"
        if tok.pad_token_id is None:
            tok.pad_token = tok.eos_token

    def close(self) -> None:
        self.model = None
        self.processor = None
        self._prompt_tokens = None
        self._static = None

    @property
    def placement(self) -> str:
        """Where the model runs, for the metadata: cpu, cuda:0, or the device map's devices."""
        if self.model is None:
            return self.device
        hf_map = getattr(self.model, "hf_device_map", None)
        if hf_map:
            return ",".join(sorted({str(d) for d in hf_map.values()}))
        return str(self.model.device)

    # -------------------------------------------------------------------------------- generation
    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        out: list[Answer | None] = [None] * len(requests)
        for batch in self.plan_batches(requests):
            for i, ans in zip(batch, self._generate_batch([requests[i] for i in batch]), strict=True):
                out[i] = ans
        return out  # type: ignore[return-value]

    def plan_batches(self, requests: Sequence[ChatRequest]) -> list[tuple[int, ...]]:
        """Batches of alike shapes, longest prompts first (see vlmproprio.backends.scheduling)."""
        for r in requests:
            if r.config.temperature != 0:
                raise BackendError(
                    f"{r.tag}: the hf backend decodes greedily (temperature 0, the paper's setting); "
                    f"got temperature={r.config.temperature}"
                )
        if not requests:
            return []
        shapes = self.request_shapes(requests)
        return [b.indices for b in plan_batches(shapes, self.max_batch_size, self.max_batch_tokens)]

    def request_shapes(self, requests: Sequence[ChatRequest]) -> list[RequestShape]:
        """Prompt length (text tokens + the tokens each image becomes) and image count of each request."""
        self.load()
        tok = self.processor.tokenizer
        if self._prompt_tokens is None or self._prompt_tokens.tokenizer is not tok:  # new, or swapped (perf/)
            self._prompt_tokens, self._size_tokens = PromptTokenCounter(tok), {}
        lengths = self._prompt_tokens.counts([self._chat_text(r) for r in requests])
        shapes = []
        for r, n_text in zip(requests, lengths, strict=True):
            # the chat text holds one placeholder token per image; the processor expands it
            n_image = sum(self._tokens_of(img) - 1 for img in r.images)
            setting = json.dumps(r.config.to_dict(), sort_keys=True)
            shapes.append(RequestShape(setting, n_text + n_image, len(r.images)))
        return shapes

    def _tokens_of(self, img: ImagePart) -> int:
        """How many tokens the processor makes of ``img`` (from its size; the pixels are not decoded). The count
        depends on the size only, so it is asked of the processor once per size (a wave's frames share one)."""
        if img.sha256 not in self._image_sizes:
            self._image_sizes[img.sha256] = _image_size(img)
        size = self._image_sizes[img.sha256]
        if size is None:  # a bad image, which fails later with its own message: only an ordering hint
            return 1
        if size not in self._size_tokens:
            self._size_tokens[size] = self._tokens_of_size(size)
        return self._size_tokens[size]

    def _tokens_of_size(self, size: tuple[int, int]) -> int:
        try:
            counts = self.processor._get_num_multimodal_tokens(image_sizes=[size])
            return int(counts["num_image_tokens"][0])
        except (AttributeError, KeyError, TypeError, ValueError, OSError):
            # only an ordering hint: a processor without the count sorts by text length and image count
            return 1

    def _compiles_decode(self) -> bool:
        if not self.static_cache or self.compile_decode is False:
            return False
        return bool(self.compile_decode) or self.model.device.type == "cuda"

    def _cache_kwargs(self, rows: int, prompt_len: int, max_new_tokens: int) -> tuple[dict, dict]:
        """generate() arguments for the KV cache, and what to record about it."""
        if not self.static_cache:
            return {}, {"kv_cache": "dynamic"}
        from transformers import CompileConfig, StaticCache

        length = round_up(prompt_len + max_new_tokens, self.cache_bucket)
        if self._static is not None and self._static[0] == (rows, length):
            cache = self._static[1]
            cache.reset()
        else:
            self._static = None  # free the old one first: at large batches a cache is gigabytes
            cache = StaticCache(config=self.model.config.get_text_config(decoder=True), max_cache_len=length)
            self._static = ((rows, length), cache)
        kwargs: dict = {"cache": cache}
        if not self._compiles_decode():
            kwargs["disable_compile"] = True
        elif self.model.device.type != "cuda":
            # transformers compiles on accelerators only unless told; CUDA graphs need a GPU, hence "default"
            compile_config = CompileConfig(mode="default")
            compile_config._compile_all_devices = True
            kwargs["compile_config"] = compile_config
        return kwargs, {"kv_cache": "static", "cache_len": length, "compiled_decode": self._compiles_decode()}

    def _generate_batch(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        """The one generation loop: same decoding settings, at most max_batch_size requests."""
        import torch

        self.load()
        cfg = requests[0].config
        texts = [self._chat_text(r) for r in requests]
        images = processor_images(self.processor, [[_decode_image(img, r) for img in r.images] for r in requests])
        inputs = self.processor(images=images, text=texts, padding=True, return_tensors="pt")
        target = self.model.device
        inputs = {
            k: (v.to(target, dtype=self.model.dtype) if torch.is_floating_point(v) else v.to(target))
            for k, v in inputs.items()
        }
        prompt_len = inputs["input_ids"].shape[1]
        prompt_counts = inputs["attention_mask"].sum(dim=1).tolist()
        check_context(self.weights.model_id, self.model.config, requests, prompt_counts, cfg.max_new_tokens)
        gen = dict(max_new_tokens=cfg.max_new_tokens, **PURE_GREEDY)
        if cfg.min_new_tokens:
            gen["min_new_tokens"] = cfg.min_new_tokens
        t0 = time.perf_counter()
        with torch.inference_mode():  # a kept static cache holds inference tensors: reset it in here too
            cache_kwargs, cache_meta = self._cache_kwargs(len(requests), prompt_len, cfg.max_new_tokens)
            seq = self.model.generate(**inputs, **gen, **cache_kwargs)
        if target.type == "cuda":
            torch.cuda.synchronize(target)
        elapsed = time.perf_counter() - t0
        new_tokens = seq[:, prompt_len:]
        decoded = self.processor.tokenizer.batch_decode(new_tokens, skip_special_tokens=True)
        ends = _eos_ids(self.model)
        answers = []
        for row, text, n_prompt in zip(new_tokens.tolist(), decoded, prompt_counts, strict=True):
            n_new = next((j for j, t in enumerate(row) if t in ends), len(row))
            meta = AnswerMeta(
                **self.identity(),
                device=self.placement,
                prompt_tokens=int(n_prompt),
                completion_tokens=n_new,
                latency_s=elapsed / len(requests),
                extra={
                    "batch_size": len(requests),
                    "batch_latency_s": elapsed,
                    "padded_prompt_tokens": int(prompt_len),
                    "processor": self.processor_via,
                    **cache_meta,
                },
            )
            answers.append(Answer(text=text.strip(), meta=meta))
        return answers

    def _chat_text(self, request: ChatRequest) -> str:
        conversation = [
            {
                "role": m.role,
                "content": [
                    {"type": "image"} if isinstance(p, ImagePart) else {"type": "text", "text": p.text} for p in m.parts
                ],
            }
            for m in request.messages
        ]
        switch = {} if request.config.thinking is None else {"enable_thinking": request.config.thinking}
        # extra keyword arguments reach the template as variables; one without the switch ignores it
        return self.processor.apply_chat_template(conversation, add_generation_prompt=True, tokenize=False, **switch)


def _eos_ids(model) -> set[int]:
    eos = model.generation_config.eos_token_id
    ids = set(eos if isinstance(eos, list) else [eos] if eos is not None else [])
    if model.generation_config.pad_token_id is not None:
        ids.add(model.generation_config.pad_token_id)
    return ids


def _image_size(img: ImagePart) -> tuple[int, int] | None:
    """(height, width) of ``img`` from its header; None for an image that PIL cannot open."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(img.data)) as im:
            width, height = im.size
    except (OSError, ValueError):
        return None
    return (height, width)


def _decode_image(img: ImagePart, request: ChatRequest):
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(img.data)) as im:
            return im.convert("RGB")
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise BackendError(f"{request.tag}: cannot decode image {img.sha256[:12]} ({exc})") from exc


def _resolve_dtype(dtype: str, device: str) -> str:
    if dtype != "auto":
        return dtype
    if device == "cpu":
        return "float32"
    import torch

    if torch.cuda.is_available() and torch.cuda.is_bf16_supported():
        return "bfloat16"
    return "float32"


# ---------------------------------------------------------------------------------------------- the hf kind


@dataclass(frozen=True)
class HFSettings:
    """A local transformers model: the keyword arguments of HFBackend a run sets.

    Only ``dtype`` and ``attn_implementation`` change answers (they are in the cache key); the rest is how fast.
    """

    device: str = "cpu"  # cpu | cuda | cuda:N | auto (accelerate device map)
    dtype: str = "auto"  # auto (float32 on CPU, bfloat16 on GPU) | float32 | bfloat16 | float16
    attn_implementation: str = "sdpa"  # eager | sdpa | flash_attention_2 | ...
    max_batch_size: int = 8  # requests per generate() call
    threads: int | None = None  # torch threads (pin to 1 for bit-identical CPU runs)
    static_cache: bool = False  # static KV cache per batch, decode step compiled on a GPU (not in the cache key)
    max_batch_tokens: int | None = None  # cap on rows x longest prompt per batch (None: 16384 on a CPU, else none)
    allow_download: bool = False  # fetch missing weights from the Hugging Face Hub (off: local files only)


def hf_slug(name: str, weights: str) -> str:
    """A folder is named by its last part (its absolute path differs between machines), a repo id in full."""
    w = weights.rstrip("/")
    looks_like_path = w.startswith(("/", ".", "~")) or w.count("/") > 1
    readable = w.rsplit("/", 1)[-1] if looks_like_path else w
    return file_slug(name, "hf", w, readable, lossless=not looks_like_path)


def _create_hf(ref: ModelRef, settings: BackendSettings) -> Backend:
    from vlmproprio.backends.tiny import ensure_tiny_model, models_dir

    weights, model_id = ref.weights, None
    if ref.tiny_family:
        weights, model_id = str(ensure_tiny_model(ref.tiny_family, settings.home)), ref.name
    memo = models_dir(settings.home)
    return HFBackend(weights, model_id=model_id, revision_memo=memo, **asdict(settings.for_kind("hf")))


def _missing_modules(*names: str) -> list[str]:
    import importlib.util

    return [n for n in names if importlib.util.find_spec(n) is None]


def _hf_live(ref: ModelRef, settings: BackendSettings) -> Availability:
    if missing := _missing_modules("torch", "transformers"):
        return Availability(False, f"needs {', '.join(missing)}: pip install 'vlmproprio[hf]'")
    if ref.tiny_family:
        return Availability(True, "tiny model, built locally on first use")
    ok, why = hf_weights_available(ref.weights)
    allow_download = settings.for_kind("hf").allow_download
    if not ok and allow_download and "/" in ref.weights and not ref.weights.startswith(("/", ".")):
        return Availability(True, f"{ref.weights} will be downloaded from the Hugging Face Hub (--allow-download)")
    return Availability(ok, why)


_HF_OPTIONS = (
    KindOption(
        "--allow-download",
        "allow_download",
        {
            "run": "fetch missing hf: weights from the Hugging Face Hub when it is reachable (default: local files only)",
            "models": "count hf: weights on the Hub as available",
        },
        action="store_true",
    ),
    KindOption("--device", "device", {"run": "cpu | cuda | cuda:N | auto (default cpu)"}, default="cpu"),
    KindOption("--dtype", "dtype", {"run": "auto | float32 | bfloat16 | float16 (default auto)"}, default="auto"),
    KindOption(
        "--attn",
        "attn_implementation",
        {"run": "attention implementation: eager | sdpa | flash_attention_2"},
        default="sdpa",
    ),
    KindOption("--batch-size", "max_batch_size", {"run": "requests per generate() call (default 8)"}, int, 8),
    KindOption("--threads", "threads", {"run": "torch threads (pin to 1 for bit-identical CPU runs)"}, int),
    KindOption("--judge-threads", "threads", {"score": "torch threads of a local judge (default 1)"}, int, 1),
    KindOption(
        "--batch-tokens",
        "max_batch_tokens",
        {"run": "cap on a batch's rows x longest prompt, in tokens (default: 16384 on a CPU, none on a GPU)"},
        int,
    ),
    KindOption(
        "--static-cache",
        "static_cache",
        {"run": "static KV cache; on a GPU the decode step is compiled (first batches pay ~1 min; pays on long runs)"},
        action="store_true",
    ),
)

register_kind(
    KindSpec(
        kind="hf",
        create=_create_hf,
        live=_hf_live,
        prefix="hf:",
        syntax="hf:<folder or HF repo id>",
        label="transformers",
        slug=hf_slug,
        settings_type=HFSettings,
        options=_HF_OPTIONS,
        option_group="local models (hf)",
    )
)
