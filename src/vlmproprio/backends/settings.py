"""How to run a model: one settings type per backend kind, and the bundle a run carries.

Each backend takes its own settings as keyword arguments of the same names (``HFBackend(weights,
**asdict(settings.hf))``), so a setting is spelled once here, not again in every layer. Only ``dtype`` and
``attn_implementation`` change answers (they are in the cache key); everything else is how fast.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from vlmproprio.models import DEFAULT_CASSETTE_DIR


@dataclass(frozen=True)
class HFSettings:
    """A local transformers model (vlmproprio.backends.hf)."""

    device: str = "cpu"  # cpu | cuda | cuda:N | auto (accelerate device map)
    dtype: str = "auto"  # auto (float32 on CPU, bfloat16 on GPU) | float32 | bfloat16 | float16
    attn_implementation: str = "sdpa"  # eager | sdpa | flash_attention_2 | ...
    max_batch_size: int = 8  # requests per generate() call
    threads: int | None = None  # torch threads (pin to 1 for bit-identical CPU runs)
    static_cache: bool = False  # static KV cache per batch, decode step compiled on a GPU (not in the cache key)
    max_batch_tokens: int | None = None  # cap on rows x longest prompt per batch (None: 16384 on a CPU, else none)
    allow_download: bool = False  # fetch missing weights from the Hugging Face Hub (off: local files only)


@dataclass(frozen=True)
class OpenAISettings:
    """A model behind an OpenAI-compatible server (vlmproprio.backends.openai)."""

    base_url: str | None = None  # server URL, e.g. http://127.0.0.1:8000/v1 for vLLM
    api_key_env: str = "OPENAI_API_KEY"  # the environment variable holding the key
    concurrency: int = 4  # requests in flight
    timeout_s: float = 120.0  # per request
    max_retries: int = 4  # retries on 429 / 5xx / timeouts / connection errors / malformed JSON


_HF_FIELDS = frozenset(f.name for f in fields(HFSettings))
_OPENAI_FIELDS = frozenset(f.name for f in fields(OpenAISettings))


@dataclass(frozen=True)
class BackendSettings:
    """Everything a run says about how to run its models."""

    hf: HFSettings = field(default_factory=HFSettings)
    openai: OpenAISettings = field(default_factory=OpenAISettings)
    cassette_dir: Path = DEFAULT_CASSETTE_DIR  # replay: where <slug>.jsonl cassettes live
    home: Path | None = None  # cache root where tiny models are built in models/ (None: locations.cache_root())

    @classmethod
    def of(cls, **options) -> BackendSettings:
        """Settings from flat options (``threads=1, base_url=...``), each routed to the kind it belongs to;
        an unknown name is a TypeError, as for any keyword argument."""
        return cls().with_options(**options)

    def with_options(self, **options) -> BackendSettings:
        """These settings with some flat options changed (see :meth:`of`)."""
        hf = {k: v for k, v in options.items() if k in _HF_FIELDS}
        oa = {k: v for k, v in options.items() if k in _OPENAI_FIELDS}
        own = {k: v for k, v in options.items() if k in ("cassette_dir", "home")}
        if unknown := set(options) - set(hf) - set(oa) - set(own):
            raise TypeError(f"unknown backend setting(s): {', '.join(sorted(unknown))}")
        return replace(self, hf=replace(self.hf, **hf), openai=replace(self.openai, **oa), **own)

    def record(self) -> dict:
        """The settings as run.json records them: flat, without local paths."""
        return {**asdict(self.hf), **asdict(self.openai)}
