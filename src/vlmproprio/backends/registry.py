"""Model references → backends: one dispatch table.

``KINDS`` maps a backend kind (``ModelRef.kind``: hf, openai, reference, ...) to its KindSpec, which its
backend module registers (vlmproprio.kinds): how to build its backend and how to tell, without building
anything heavy, whether it can run live here. ``create_backend`` and
``model_availability`` both read it; a model with a cassette is answered by ``ReplayBackend`` in replay mode
whatever its kind, except the rule-based captioners, which need no cassette.

This module imports no heavy library: backends import theirs when they are built.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from vlmproprio.backends.base import Availability, Backend, BackendError
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.errors import UsageError
from vlmproprio.kinds import KindSpec, kind_spec, kind_specs
from vlmproprio.models import REGISTRY, ModelRef, resolve_model
from vlmproprio.options import ANSWER_MODES, AUTO_MODE

__all__ = [
    "KINDS",
    "Availability",
    "BackendSettings",
    "create_backend",
    "format_availability",
    "model_availability",
    "record_hint",
    "resolve_mode",
]


class _Kinds(Mapping[str, KindSpec]):
    """The backend kinds by name, read from their registrations each time (a kind registered later is seen)."""

    def __getitem__(self, kind: str) -> KindSpec:
        return kind_spec(kind)

    def __iter__(self) -> Iterator[str]:
        return iter([spec.kind for spec in kind_specs()])

    def __len__(self) -> int:
        return len(kind_specs())


KINDS: Mapping[str, KindSpec] = _Kinds()


def record_hint(ref: ModelRef) -> str:
    return (
        f"record one where the model runs (`vlmproprio run --model {ref.name} --mode record`; answers already in "
        f"the response cache: `vlmproprio cassette export --model {ref.name}`)"
    )


def _check_mode(mode: str) -> None:
    if mode not in (AUTO_MODE, *ANSWER_MODES):
        raise UsageError(f"unknown mode {mode!r}; choose from {', '.join((AUTO_MODE, *ANSWER_MODES))}")


def resolve_mode(model: str | ModelRef, mode: str, settings: BackendSettings | None = None) -> str:
    """``auto`` made concrete for one model: ``replay`` when it has a cassette, else ``live`` (the reference
    captioner has none: it runs, through the response cache). Other modes are returned as they are."""
    _check_mode(mode)
    if mode != AUTO_MODE:
        return mode
    settings = settings or BackendSettings()
    return "replay" if resolve_model(model).cassette(settings.cassette_dir).is_file() else "live"


def _replay_backend(ref: ModelRef, settings: BackendSettings) -> Backend:
    from vlmproprio.backends.replay import ReplayBackend
    from vlmproprio.episodes import check_fixture_file

    path = ref.cassette(settings.cassette_dir)
    if not path.is_file():
        raise BackendError(f"no cassette for model {ref.name!r} at {path}; " + record_hint(ref))
    backend = ReplayBackend(path, model=ref.slug)  # a damaged line: an error naming file and line
    check_fixture_file(path)  # a line edited and re-checksummed: the manifest's sha256 differs
    return backend


def create_backend(model: str | ModelRef, mode: str = "live", settings: BackendSettings | None = None) -> Backend:
    """The backend that answers for ``model`` in ``mode`` (replay: its cassette; reference: always itself)."""
    settings = settings or BackendSettings()
    ref = resolve_model(model)
    kind = KINDS[ref.kind]
    if resolve_mode(ref, mode, settings) == "replay" and kind.needs_cassette:
        return _replay_backend(ref, settings)
    return kind.create(ref, settings)


def model_availability(
    model: str | ModelRef, mode: str = "live", settings: BackendSettings | None = None
) -> Availability:
    """Whether ``model`` can run here in ``mode`` without building anything heavy, and why not.

    Unknown or unsafe names raise ModelNameError: a typo is an error, not a skip.
    """
    settings = settings or BackendSettings()
    _check_mode(mode)
    ref = resolve_model(model)
    kind = KINDS[ref.kind]
    if not kind.needs_cassette:
        return kind.live(ref, settings)
    cassette = ref.cassette(settings.cassette_dir)
    if mode == AUTO_MODE:
        live = kind.live(ref, settings)
        if cassette.is_file():
            return Availability(True, f"cassette {cassette}")
        if live:
            return live
        return Availability(False, f"neither a cassette nor the model: {live.reason}; or " + record_hint(ref))
    if mode == "replay":
        if cassette.is_file():
            return Availability(True, f"cassette {cassette}")
        return Availability(False, f"no cassette {cassette}; " + record_hint(ref))
    return kind.live(ref, settings)


def format_availability(settings: BackendSettings, names: list[str] | None = None) -> str:
    """Per model: its cassette in ``settings.cassette_dir`` (replay) and whether it can run live here, with how to
    get what is missing. One block per model; the reason line is the one the benchmark skips with."""
    lines = []
    for ref in map(resolve_model, names or list(REGISTRY)):
        kind = KINDS[ref.kind]
        if not kind.needs_cassette:
            lines.append(f"{ref.name}  [{ref.kind}]  replay: yes  live: yes  (rules, needs nothing)")
            continue
        cassette = ref.cassette(settings.cassette_dir)
        has_cassette = cassette.is_file()
        live = kind.live(ref, settings)
        lines.append(
            f"{ref.name}  [{ref.kind}: {ref.weights}]  replay: {'yes' if has_cassette else 'no'}  "
            f"live: {'yes' if live else 'no'}"
        )
        lines.append(f"    cassette: {cassette if has_cassette else 'none; ' + record_hint(ref)}")
        lines.append(f"    live: {live.reason}")
    return "\n".join(lines)
