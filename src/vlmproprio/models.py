"""Model names, resolved once into a typed reference.

A model is named three ways:

* a short registry name (``REGISTRY`` below, e.g. ``qwen2-vl``, ``gpt-4v``, ``tiny-qwen2-vl``, ``reference``);
* ``hf:<local folder or Hugging Face repo id>``: any transformers VLM, offline;
* ``openai:<model name>``: any model behind an OpenAI-compatible server (``--base-url`` for vLLM, SGLang).

A prefix belongs to the backend module that declares its kind (vlmproprio.kinds): the registry's short names
are here, every ``<prefix><weights>`` form is read from the kinds.

:func:`resolve_model` is the one place a name is parsed: it checks the name and returns a
:class:`ModelRef` (name, folder-safe slug, backend kind, weights, default answer length) that everything
downstream passes around instead of the string. Which backend answers for a reference, and whether it can
run here, is vlmproprio.backends.registry.
"""

from __future__ import annotations

import functools
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.errors import UsageError, did_you_mean
from vlmproprio.kinds import kind_spec, kind_specs

TINY_PREFIX = "tiny:"
STATE_RULES = "state-aware rules, NOT a VLM"  # the "weights" of `reference-state`, as `vlmproprio models` shows them
DEFAULT_CASSETTE_DIR = Path("fixtures") / "responses"
# The tiny families built by vlmproprio.backends.tiny_families, with the name their registry entry shows.
TINY_FAMILY_LABELS: dict[str, str] = {
    "qwen3-vl": "Qwen3-VL",
    "gemma3": "Gemma 3",
    "idefics3": "Idefics3 (SmolVLM)",
    "internvl": "InternVL",
    "llava-onevision": "LLaVA-OneVision",
    "mistral3": "Mistral 3",
    "glm4v": "GLM-4.1V",
    "mllama": "Mllama (Llama 3.2 Vision)",
    "llava-next": "LLaVA-NeXT",
    "idefics2": "Idefics2",
    "smolvlm": "SmolVLM2",
}
MAX_NAME_LEN = 200
_SLUG_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,119}$")
_DIGEST_TAIL = re.compile(r"-[0-9a-f]{8}$")


class ModelNameError(UsageError):
    """A model name that is unknown or unsafe."""


@dataclass(frozen=True)
class ModelRef:
    """A model, resolved: what every stage after the front doors gets instead of the name."""

    name: str  # as the user wrote it (run.json, messages)
    slug: str  # one safe path component: transcripts/<slug>/, responses/<slug>.jsonl, baselines
    kind: str  # a backend kind (vlmproprio.kinds): "hf" | "openai" | "reference" | ...
    weights: str  # HF repo id or folder | OpenAI model name | "tiny:<family>" | "" or STATE_RULES (reference)
    description: str
    # default answer length; tiny random models write gibberish to the limit, so theirs is short
    max_new_tokens: int = 512

    @property
    def is_rules(self) -> bool:
        """The rule-based captioners: no model, the same answers in every mode, no cassette needed."""
        return not kind_spec(self.kind).needs_cassette

    @property
    def tiny_family(self) -> str | None:
        """The family of a tiny random model the suite builds itself (``tiny:qwen2-vl`` -> ``qwen2-vl``)."""
        return self.weights[len(TINY_PREFIX) :] if self.weights.startswith(TINY_PREFIX) else None

    def cassette(self, cassette_dir: Path | str = DEFAULT_CASSETTE_DIR) -> Path:
        """Where this model's cassette lives in ``cassette_dir``."""
        base = Path(cassette_dir)
        path = base / f"{self.slug}.jsonl"
        if path.resolve().parent != base.resolve():  # belt and braces: a slug is one component
            raise ModelNameError(f"model name {self.name!r} would leave {base}")
        return path

    def __str__(self) -> str:
        return self.name


def _registered(name: str, kind: str, weights: str, description: str, max_new_tokens: int = 512) -> ModelRef:
    return ModelRef(name, name, kind, weights, description, max_new_tokens)


REGISTRY: dict[str, ModelRef] = {
    s.name: s
    for s in (
        _registered("qwen2-vl", "hf", "Qwen/Qwen2-VL-2B-Instruct", "Qwen2-VL 2B Instruct, open weights"),
        _registered("qwen2-vl-7b", "hf", "Qwen/Qwen2-VL-7B-Instruct", "Qwen2-VL 7B Instruct, open weights"),
        _registered("qwen2.5-vl", "hf", "Qwen/Qwen2.5-VL-3B-Instruct", "Qwen2.5-VL 3B Instruct, open weights"),
        _registered("qwen2.5-vl-7b", "hf", "Qwen/Qwen2.5-VL-7B-Instruct", "Qwen2.5-VL 7B Instruct, open weights"),
        _registered("llava", "hf", "llava-hf/llava-1.5-7b-hf", "LLaVA-1.5 7B (transformers port), open weights"),
        _registered(
            "llava-onevision",
            "hf",
            "llava-hf/llava-onevision-qwen2-0.5b-ov-hf",
            "LLaVA-OneVision 0.5B (transformers port), open weights",
        ),
        _registered(
            "llava-onevision-7b",
            "hf",
            "llava-hf/llava-onevision-qwen2-7b-ov-hf",
            "LLaVA-OneVision 7B (transformers port), open weights",
        ),
        # The families of tiny_families, at their published sizes (docs/models.md: what a frame costs in each,
        # whether Process 3 fits the context, and what needs torchvision)
        _registered("qwen3-vl", "hf", "Qwen/Qwen3-VL-2B-Instruct", "Qwen3-VL 2B Instruct, open weights"),
        _registered("qwen3-vl-4b", "hf", "Qwen/Qwen3-VL-4B-Instruct", "Qwen3-VL 4B Instruct, open weights"),
        _registered("gemma3", "hf", "google/gemma-3-4b-it", "Gemma 3 4B instruction-tuned, open weights (gated)"),
        _registered("gemma3-12b", "hf", "google/gemma-3-12b-it", "Gemma 3 12B instruction-tuned, open weights (gated)"),
        _registered(
            "smolvlm", "hf", "HuggingFaceTB/SmolVLM-256M-Instruct", "SmolVLM 256M Instruct (Idefics3), open weights"
        ),
        _registered(
            "smolvlm-2.2b", "hf", "HuggingFaceTB/SmolVLM-Instruct", "SmolVLM 2.2B Instruct (Idefics3), open weights"
        ),
        _registered("smolvlm2", "hf", "HuggingFaceTB/SmolVLM2-2.2B-Instruct", "SmolVLM2 2.2B Instruct, open weights"),
        _registered(
            "smolvlm2-500m",
            "hf",
            "HuggingFaceTB/SmolVLM2-500M-Video-Instruct",
            "SmolVLM2 500M Video Instruct, open weights",
        ),
        _registered("internvl3", "hf", "OpenGVLab/InternVL3-1B-hf", "InternVL3 1B (transformers port), open weights"),
        _registered(
            "internvl3-2b", "hf", "OpenGVLab/InternVL3-2B-hf", "InternVL3 2B (transformers port), open weights"
        ),
        _registered(
            "mistral3",
            "hf",
            "mistralai/Mistral-Small-3.1-24B-Instruct-2503",
            "Mistral Small 3.1 24B Instruct (Mistral 3), open weights; needs torchvision",
        ),
        _registered("glm4v", "hf", "zai-org/GLM-4.1V-9B-Thinking", "GLM-4.1V 9B Thinking, open weights"),
        _registered(
            "mllama",
            "hf",
            "meta-llama/Llama-3.2-11B-Vision-Instruct",
            "Llama 3.2 11B Vision Instruct (Mllama), open weights (gated)",
        ),
        _registered(
            "mllama-90b",
            "hf",
            "meta-llama/Llama-3.2-90B-Vision-Instruct",
            "Llama 3.2 90B Vision Instruct (Mllama), open weights (gated)",
        ),
        _registered(
            "llava-next",
            "hf",
            "llava-hf/llava-v1.6-mistral-7b-hf",
            "LLaVA-NeXT (LLaVA-1.6) Mistral 7B (transformers port), open weights",
        ),
        _registered(
            "llava-next-13b",
            "hf",
            "llava-hf/llava-v1.6-vicuna-13b-hf",
            "LLaVA-NeXT (LLaVA-1.6) Vicuna 13B (transformers port), open weights",
        ),
        _registered("idefics2", "hf", "HuggingFaceM4/idefics2-8b", "Idefics2 8B, open weights"),
        _registered(
            "idefics2-chatty",
            "hf",
            "HuggingFaceM4/idefics2-8b-chatty",
            "Idefics2 8B chatty (longer answers), open weights",
        ),
        _registered("lfm2-vl", "hf", "LiquidAI/LFM2-VL-450M", "LFM2-VL 450M, open weights; needs torchvision"),
        _registered("lfm2-vl-1.6b", "hf", "LiquidAI/LFM2-VL-1.6B", "LFM2-VL 1.6B, open weights; needs torchvision"),
        _registered(
            "gpt-4v",
            "openai",
            "gpt-4-vision-preview",
            "GPT-4V, the paper's model, through the OpenAI API (it may no longer be served: replay its cassette)",
        ),
        # a dated snapshot: the alias "gpt-4o" moves to newer snapshots, and answers cached under it would mix them
        _registered("gpt-4o", "openai", "gpt-4o-2024-08-06", "GPT-4o (the 2024-08-06 snapshot) through the OpenAI API"),
        _registered(
            "tiny-qwen2-vl", "hf", TINY_PREFIX + "qwen2-vl", "tiny random Qwen2-VL built locally; tests only", 64
        ),
        _registered(
            "tiny-qwen2.5-vl", "hf", TINY_PREFIX + "qwen2.5-vl", "tiny random Qwen2.5-VL built locally; tests only", 64
        ),
        _registered("tiny-llava", "hf", TINY_PREFIX + "llava", "tiny random LLaVA built locally; tests only", 64),
        *(
            _registered(
                f"tiny-{family}", "hf", TINY_PREFIX + family, f"tiny random {label} built locally; tests only", 64
            )
            for family, label in TINY_FAMILY_LABELS.items()
        ),
        _registered(
            "reference",
            "reference",
            "",
            "rule-based motion-primitive captions from the state numbers; NOT a VLM (a baseline)",
        ),
        _registered(
            "reference-state",
            "reference",
            STATE_RULES,
            "rule-based, task-aware captions from the state numbers; NOT a VLM (a positive control)",
        ),
    )
}


def format_registry() -> str:
    """The registry as an aligned text table (name, backend, default weights)."""
    rows = [("name", "backend", "default weights")] + [(s.name, s.kind, s.weights or "-") for s in REGISTRY.values()]
    w0, w1 = (max(len(r[i]) for r in rows) for i in range(2))
    return "\n".join(f"{a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows)


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


def _sanitise(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._-")


def file_slug(name: str, kind: str, full: str, readable: str, lossless: bool) -> str:
    """One safe path component for a ``<kind>:<full>`` name: ``<kind>_`` and the sanitised ``readable`` part.

    The readable part can lose information (``openai:org/m`` and ``openai:org_m``; ``hf:…/run1/checkpoint-500``
    and ``hf:…/run2/checkpoint-500``; upper case on a case-insensitive disk): then (or when the caller says it
    is not ``lossless``) the slug ends in ``-`` and 8 hex digits of the sha256 of the full name, so two names
    never share a transcripts folder or a cassette. A name kept whole gets no suffix (``openai:gpt-4o``), so
    existing folders, cassettes and baselines keep their names."""
    slug = f"{kind}_{_sanitise(readable)}"
    lossless = lossless and _sanitise(readable) == readable and readable == readable.lower()
    if not lossless or _DIGEST_TAIL.search(slug):
        slug = f"{slug[:110]}-{hashlib.sha256(f'{kind}:{full}'.encode()).hexdigest()[:8]}"
    if not _SLUG_RE.match(slug) or ".." in slug or slug.split("-")[0].rstrip("_") == kind:
        raise ModelNameError(f"model name {name!r} gives no usable file name ({slug!r})")
    return slug


@functools.lru_cache(maxsize=256)
def _resolve(name: str) -> ModelRef:
    _check_name(name)
    if name in REGISTRY:
        return REGISTRY[name]
    prefixed = [spec for spec in kind_specs() if spec.prefix]
    for spec in prefixed:
        if name.startswith(spec.prefix):
            rest = name[len(spec.prefix) :].strip()
            if not rest:
                raise ModelNameError(f"{name!r}: nothing after {spec.prefix!r}")
            return ModelRef(name, spec.slug(name, rest), spec.kind, rest, f"{rest} ({spec.label})")
    known = ", ".join(REGISTRY)
    forms = ", ".join(spec.syntax for spec in prefixed)
    raise ModelNameError(f"unknown model {name!r}{did_you_mean(name, REGISTRY)}. Known: {known}; or {forms}")


def resolve_model(model: str | ModelRef) -> ModelRef:
    """The reference for any accepted model name (a reference is returned as it is); ModelNameError for unknown
    or unsafe names."""
    if isinstance(model, ModelRef):
        return model
    if not isinstance(model, str):
        raise ModelNameError(f"a model name must be text, got {type(model).__name__}")
    return _resolve(model)
