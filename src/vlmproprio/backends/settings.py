"""How to run a model: the bundle of per-kind settings a run carries.

Each backend kind declares its own settings type in its module (vlmproprio.kinds: ``KindSpec.settings_type``),
and its backend takes those settings as keyword arguments of the same names (``HFBackend(weights,
**asdict(settings.hf))``), so a setting is spelled once, in the module that uses it, not again in every layer.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from vlmproprio.kinds import kind_spec, kind_specs
from vlmproprio.models import DEFAULT_CASSETTE_DIR

_OWN = ("cassette_dir", "home")


def _kinds_with_settings() -> list:
    return [spec for spec in kind_specs() if spec.settings_type is not None]


def _default_per_kind() -> tuple[tuple[str, Any], ...]:
    return tuple((spec.kind, spec.settings_type()) for spec in _kinds_with_settings())


@dataclass(frozen=True)
class BackendSettings:
    """Everything a run says about how to run its models; ``settings.hf`` is ``settings.for_kind("hf")``."""

    cassette_dir: Path = DEFAULT_CASSETTE_DIR  # replay: where <slug>.jsonl cassettes live
    home: Path | None = None  # cache root where tiny models are built in models/ (None: locations.cache_root())
    per_kind: tuple[tuple[str, Any], ...] = field(default_factory=_default_per_kind)  # (kind, its settings)

    def for_kind(self, kind: str) -> Any:
        """The settings of one backend kind (its defaults when these settings were made before it registered)."""
        for name, settings in self.per_kind:
            if name == kind:
                return settings
        return kind_spec(kind).settings_type()

    def __getattr__(self, name: str) -> Any:
        # only called for names that are not attributes: a kind's name reads its settings
        if name.startswith("_") or name not in {spec.kind for spec in _kinds_with_settings()}:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return self.for_kind(name)

    @classmethod
    def of(cls, **options) -> BackendSettings:
        """Settings from flat options (``threads=1, base_url=...``), each routed to the kind it belongs to;
        an unknown name is a TypeError, as for any keyword argument."""
        return cls().with_options(**options)

    def with_options(self, **options) -> BackendSettings:
        """These settings with some flat options changed (see :meth:`of`)."""
        own = {k: v for k, v in options.items() if k in _OWN}
        left = set(options) - set(own)
        per_kind = []
        for spec in _kinds_with_settings():
            names = {f.name for f in fields(spec.settings_type)}
            mine = {k: v for k, v in options.items() if k in names}
            left -= set(mine)
            per_kind.append((spec.kind, mine))
        if left:
            raise TypeError(f"unknown backend setting(s): {', '.join(sorted(left))}")
        changed = tuple((kind, replace(self.for_kind(kind), **mine)) for kind, mine in per_kind)
        return replace(self, per_kind=changed, **own)

    def record(self) -> dict:
        """The settings as run.json records them: flat, kind after kind, without local paths."""
        out: dict = {}
        for spec in _kinds_with_settings():
            out.update(asdict(self.for_kind(spec.kind)))
        return out
