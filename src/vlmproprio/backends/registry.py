"""Model names → backends.

A model is named three ways:

* a short registry name (``REGISTRY`` below, e.g. ``qwen2-vl``, ``gpt-4v``, ``tiny-qwen2-vl``, ``reference``);
* ``hf:<local folder or Hugging Face repo id>``: any transformers VLM, offline;
* ``openai:<model name>``: any model behind an OpenAI-compatible server (``--base-url`` for vLLM, SGLang).

``model_slug(name)`` turns an accepted name into one safe path component (cassette
file names, run-dir folders). ``create_backend`` builds the backend for a name and a
mode; ``model_availability`` says whether a model can run here and, if not, how to
get it (the benchmark skips unavailable cells with that reason).

This module imports no heavy library: backends import theirs when they are built.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from vlmproprio.backends.base import Backend, BackendError
from vlmproprio.errors import UsageError
from vlmproprio.options import ANSWER_MODES as MODES

AUTO_MODE = "auto"  # replay when a cassette exists, else live (vlmproprio.options.DEFAULT_MODE)
HF_PREFIX = "hf:"
OPENAI_PREFIX = "openai:"
TINY_PREFIX = "tiny:"
STATE_RULES = "state-aware rules, NOT a VLM"  # the "weights" of `reference-state`, as `vlmproprio models` shows them
DEFAULT_CASSETTE_DIR = Path("fixtures") / "responses"
MAX_NAME_LEN = 200
_SLUG_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,119}$")


class ModelNameError(UsageError):
    """A model name that is unknown or unsafe."""


@dataclass(frozen=True)
class ModelSpec:
    name: str
    backend: str  # "hf" | "openai" | "reference"
    weights: str  # HF repo id or folder | OpenAI model name | "tiny:<family>" | "" or STATE_RULES (reference)
    description: str
    # default answer length; tiny random models write gibberish to the limit, so theirs is short
    max_new_tokens: int = 512


REGISTRY: dict[str, ModelSpec] = {
    s.name: s
    for s in (
        ModelSpec("qwen2-vl", "hf", "Qwen/Qwen2-VL-2B-Instruct", "Qwen2-VL 2B Instruct, open weights"),
        ModelSpec("qwen2-vl-7b", "hf", "Qwen/Qwen2-VL-7B-Instruct", "Qwen2-VL 7B Instruct, open weights"),
        ModelSpec("qwen2.5-vl", "hf", "Qwen/Qwen2.5-VL-3B-Instruct", "Qwen2.5-VL 3B Instruct, open weights"),
        ModelSpec("qwen2.5-vl-7b", "hf", "Qwen/Qwen2.5-VL-7B-Instruct", "Qwen2.5-VL 7B Instruct, open weights"),
        ModelSpec("llava", "hf", "llava-hf/llava-1.5-7b-hf", "LLaVA-1.5 7B (transformers port), open weights"),
        ModelSpec(
            "llava-onevision",
            "hf",
            "llava-hf/llava-onevision-qwen2-0.5b-ov-hf",
            "LLaVA-OneVision 0.5B (transformers port), open weights",
        ),
        ModelSpec(
            "gpt-4v",
            "openai",
            "gpt-4-vision-preview",
            "GPT-4V, the paper's model, through the OpenAI API (it may no longer be served: replay its cassette)",
        ),
        ModelSpec("gpt-4o", "openai", "gpt-4o", "GPT-4o through the OpenAI API"),
        ModelSpec(
            "tiny-qwen2-vl", "hf", TINY_PREFIX + "qwen2-vl", "tiny random Qwen2-VL built locally; tests only", 64
        ),
        ModelSpec(
            "tiny-qwen2.5-vl", "hf", TINY_PREFIX + "qwen2.5-vl", "tiny random Qwen2.5-VL built locally; tests only", 64
        ),
        ModelSpec("tiny-llava", "hf", TINY_PREFIX + "llava", "tiny random LLaVA built locally; tests only", 64),
        ModelSpec(
            "reference",
            "reference",
            "",
            "rule-based motion-primitive captions from the state numbers; NOT a VLM (a baseline)",
        ),
        ModelSpec(
            "reference-state",
            "reference",
            STATE_RULES,
            "rule-based, task-aware captions from the state numbers; NOT a VLM (a positive control)",
        ),
    )
}


def format_registry() -> str:
    """The registry as an aligned text table (name, backend, default weights)."""
    rows = [("name", "backend", "default weights")] + [(s.name, s.backend, s.weights or "-") for s in REGISTRY.values()]
    w0, w1 = (max(len(r[i]) for r in rows) for i in range(2))
    return "\n".join(f"{a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows)


def format_availability(settings: BackendSettings, names: list[str] | None = None) -> str:
    """Per model: its cassette in ``settings.cassette_dir`` (replay) and whether it can run live here, with how to
    get what is missing. One block per model; the reason line is the one the benchmark skips with."""
    lines = []
    for name in names or list(REGISTRY):
        spec = parse_model_name(name)
        cassette = cassette_path(name, settings.cassette_dir)
        if spec.backend == "reference":
            lines.append(f"{name}  [{spec.backend}]  replay: yes  live: yes  (rules, needs nothing)")
            continue
        has_cassette = cassette.is_file()
        live = model_availability(name, "live", settings)
        lines.append(
            f"{name}  [{spec.backend}: {spec.weights}]  replay: {'yes' if has_cassette else 'no'}  "
            f"live: {'yes' if live else 'no'}"
        )
        lines.append(f"    cassette: {cassette if has_cassette else 'none; ' + _record_hint(name)}")
        lines.append(f"    live: {live.reason}")
    return "\n".join(lines)


def _check_name(name: object) -> str:
    if not isinstance(name, str) or not name.strip():
        raise ModelNameError("empty model name")
    if len(name) > MAX_NAME_LEN:
        raise ModelNameError(f"model name longer than {MAX_NAME_LEN} characters")
    if any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise ModelNameError(f"model name {name!r} contains control characters (NUL, newline, ...)")
    if not name.isprintable():  # U+2028 / U+2029 split printed lines; format characters hide text
        raise ModelNameError(f"model name {name!r} contains a line separator or other unprintable character")
    if ".." in name or "\\" in name:
        raise ModelNameError(f"model name {name!r} contains '..' or a backslash; refused (it could leave a folder)")
    return name


def parse_model_name(name: str) -> ModelSpec:
    """The spec for any accepted model name; ModelNameError for unknown or unsafe names."""
    _check_name(name)
    for prefix, backend in ((HF_PREFIX, "hf"), (OPENAI_PREFIX, "openai")):
        if name.startswith(prefix):
            rest = name[len(prefix) :].strip()
            if not rest:
                raise ModelNameError(f"{name!r}: nothing after {prefix!r}")
            return ModelSpec(name, backend, rest, f"{rest} ({'transformers' if backend == 'hf' else 'OpenAI API'})")
    if name in REGISTRY:
        return REGISTRY[name]
    known = ", ".join(REGISTRY)
    raise ModelNameError(f"unknown model {name!r}. Known: {known}; or hf:<folder or HF repo id>, openai:<model name>")


def _sanitise(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._-")


_DIGEST_TAIL = re.compile(r"-[0-9a-f]{8}$")


def model_slug(name: str) -> str:
    """One safe path component per model: registry names as they are, ``hf_…``/``openai_…`` otherwise.

    The readable part of an ``hf:``/``openai:`` name can lose information (``openai:org/m`` and
    ``openai:org_m``; ``hf:…/run1/checkpoint-500`` and ``hf:…/run2/checkpoint-500``; upper case on a
    case-insensitive disk): then the slug ends in ``-`` and 8 hex digits of the sha256 of the full name, so
    two names never share a transcripts folder or a cassette. A name kept whole gets no suffix (registry
    names, ``openai:gpt-4o``), so existing folders, cassettes and baselines keep their names."""
    spec = parse_model_name(name)
    if name in REGISTRY:
        return name
    if spec.backend == "hf":
        w = spec.weights.rstrip("/")
        # a folder is named by its last part (its absolute path differs between machines), a repo id in full
        looks_like_path = w.startswith(("/", ".", "~")) or w.count("/") > 1
        readable = w.rsplit("/", 1)[-1] if looks_like_path else w
        slug, lossless = "hf_" + _sanitise(readable), not looks_like_path
    else:
        w = readable = spec.weights
        slug, lossless = "openai_" + _sanitise(readable), True
    lossless = lossless and _sanitise(readable) == readable and readable == readable.lower()
    if not lossless or _DIGEST_TAIL.search(slug):
        full = f"{spec.backend}:{w}"
        slug = f"{slug[:110]}-{hashlib.sha256(full.encode('utf-8')).hexdigest()[:8]}"
    if not _SLUG_RE.match(slug) or ".." in slug or slug.split("-")[0].rstrip("_") in ("hf", "openai"):
        raise ModelNameError(f"model name {name!r} gives no usable file name ({slug!r})")
    return slug


def cassette_path(name: str, cassette_dir: Path | str = DEFAULT_CASSETTE_DIR) -> Path:
    base = Path(cassette_dir)
    path = base / f"{model_slug(name)}.jsonl"
    if path.resolve().parent != base.resolve():  # belt and braces: a slug is one component
        raise ModelNameError(f"model name {name!r} would leave {base}")
    return path


@dataclass(frozen=True)
class BackendSettings:
    """How to run a model. Only dtype and attn_implementation change answers (they are in the cache key)."""

    device: str = "cpu"  # hf: cpu | cuda | cuda:N | auto (accelerate device map)
    dtype: str = "auto"  # hf: auto (float32 on CPU, bfloat16 on GPU) | float32 | bfloat16 | float16
    attn_implementation: str = "sdpa"  # hf: eager | sdpa | flash_attention_2 | ...
    max_batch_size: int = 8  # hf: requests per generate() call
    threads: int | None = None  # hf: torch threads (pin to 1 for bit-identical CPU runs)
    static_cache: bool = False  # hf: static KV cache per batch, decode step compiled on a GPU (not in the cache key)
    max_batch_tokens: int | None = None  # hf: cap on rows x longest prompt per batch (None: 16384 on a CPU, else none)
    base_url: str | None = None  # openai: server URL, e.g. http://127.0.0.1:8000/v1 for vLLM
    api_key_env: str = "OPENAI_API_KEY"  # openai: the environment variable holding the key
    concurrency: int = 4  # openai: requests in flight
    timeout_s: float = 120.0  # openai: per request
    max_retries: int = 4  # openai: retries on 429 / 5xx / timeouts / connection errors / malformed JSON
    cassette_dir: Path = DEFAULT_CASSETTE_DIR  # replay: where <slug>.jsonl cassettes live
    home: Path | None = None  # cache root where tiny models are built in models/ (None: locations.cache_root())
    allow_download: bool = False  # hf: fetch missing weights from the Hugging Face Hub (off: local files only)
    extra: dict = field(default_factory=dict)


def _record_hint(name: str) -> str:
    return (
        f"record one where the model runs (`vlmproprio run --model {name} --mode record`; answers already in "
        f"the response cache: `vlmproprio cassette export --model {name}`)"
    )


def resolve_mode(name: str, mode: str, settings: BackendSettings | None = None) -> str:
    """``auto`` made concrete for one model: ``replay`` when it has a cassette, else ``live`` (the reference
    captioner has none: it runs, through the response cache). Other modes are returned as they are."""
    if mode != AUTO_MODE:
        return mode
    settings = settings or BackendSettings()
    return "replay" if cassette_path(name, settings.cassette_dir).is_file() else "live"


def _check_mode(mode: str) -> None:
    if mode not in (AUTO_MODE, *MODES):
        raise UsageError(f"unknown mode {mode!r}; choose from {', '.join((AUTO_MODE, *MODES))}")


def create_backend(name: str, mode: str = "live", settings: BackendSettings | None = None) -> Backend:
    """The backend that answers for ``name`` in ``mode`` (replay: its cassette; reference: always itself)."""
    settings = settings or BackendSettings()
    _check_mode(mode)
    mode = resolve_mode(name, mode, settings)
    spec = parse_model_name(name)
    if spec.backend == "reference":
        if spec.weights == STATE_RULES:
            from vlmproprio.backends.reference_state import ReferenceStateBackend

            return ReferenceStateBackend()  # deterministic rules, no model: the same in every mode
        from vlmproprio.backends.reference import ReferenceBackend

        return ReferenceBackend()  # deterministic rules, no model: the same in every mode
    if mode == "replay":
        from vlmproprio.backends.replay import ReplayBackend

        path = cassette_path(name, settings.cassette_dir)
        if not path.is_file():
            raise BackendError(f"no cassette for model {name!r} at {path}; " + _record_hint(name))
        from vlmproprio.episodes import check_fixture_file

        backend = ReplayBackend(path, model=model_slug(name))  # a damaged line: an error naming file and line
        check_fixture_file(path)  # a line edited and re-checksummed: the manifest's sha256 differs
        return backend
    if spec.backend == "hf":
        from vlmproprio.backends.hf import HFBackend

        weights, model_id = spec.weights, None
        if weights.startswith(TINY_PREFIX):
            from vlmproprio.backends.tiny import ensure_tiny_model

            weights, model_id = str(ensure_tiny_model(weights[len(TINY_PREFIX) :], settings.home)), spec.name
        return HFBackend(
            weights,
            model_id=model_id,
            dtype=settings.dtype,
            device=settings.device,
            attn_implementation=settings.attn_implementation,
            max_batch_size=settings.max_batch_size,
            threads=settings.threads,
            static_cache=settings.static_cache,
            max_batch_tokens=settings.max_batch_tokens,
            allow_download=settings.allow_download,
        )
    from vlmproprio.backends.openai import OpenAIBackend

    return OpenAIBackend(
        spec.weights,
        base_url=settings.base_url,
        api_key_env=settings.api_key_env,
        concurrency=settings.concurrency,
        timeout_s=settings.timeout_s,
        max_retries=settings.max_retries,
    )


@dataclass(frozen=True)
class Availability:
    available: bool
    reason: str

    def __bool__(self) -> bool:
        return self.available


def _missing_modules(*names: str) -> list[str]:
    return [n for n in names if importlib.util.find_spec(n) is None]


def model_availability(name: str, mode: str = "live", settings: BackendSettings | None = None) -> Availability:
    """Whether ``name`` can run here in ``mode`` without building anything heavy, and why not.

    Unknown or unsafe names raise ModelNameError: a typo is an error, not a skip.
    """
    settings = settings or BackendSettings()
    _check_mode(mode)
    spec = parse_model_name(name)
    if mode == AUTO_MODE and spec.backend != "reference":
        live = model_availability(name, "live", settings)
        if cassette_path(name, settings.cassette_dir).is_file() or live:
            return model_availability(name, resolve_mode(name, mode, settings), settings)
        return Availability(False, f"neither a cassette nor the model: {live.reason}; or " + _record_hint(name))
    if spec.backend == "reference":
        return Availability(True, "rule-based reference captioner (no model, always available)")
    if mode == "replay":
        path = cassette_path(name, settings.cassette_dir)
        if path.is_file():
            return Availability(True, f"cassette {path}")
        return Availability(False, f"no cassette {path}; " + _record_hint(name))
    if spec.backend == "hf":
        missing = _missing_modules("torch", "transformers")
        if missing:
            return Availability(False, f"needs {', '.join(missing)}: pip install 'vlmproprio[hf]'")
        if spec.weights.startswith(TINY_PREFIX):
            return Availability(True, "tiny model, built locally on first use")
        from vlmproprio.backends.hf import hf_weights_available

        ok, why = hf_weights_available(spec.weights)
        if not ok and settings.allow_download and "/" in spec.weights and not spec.weights.startswith(("/", ".")):
            return Availability(True, f"{spec.weights} will be downloaded from the Hugging Face Hub (--allow-download)")
        return Availability(ok, why)
    if _missing_modules("openai"):
        return Availability(False, "needs the openai SDK: pip install 'vlmproprio[openai]'")
    if os.environ.get(settings.api_key_env) or settings.base_url:
        return Availability(True, f"OpenAI-compatible server {settings.base_url or '(OpenAI API)'}")
    return Availability(
        False, f"set ${settings.api_key_env} (OpenAI API) or a --base-url of an OpenAI-compatible server"
    )
