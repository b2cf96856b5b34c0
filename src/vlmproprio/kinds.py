"""Backend kinds, each declared by the one backend module that answers for it.

A backend module registers its kind when it is imported (``register_kind(KindSpec(...))``): the model-name
prefix (``hf:``), how such a name becomes a folder-safe slug, its settings type, its command-line options, how
to build its backend and how to tell cheaply whether it can run here. Model names (vlmproprio.models), the
backend settings, the dispatch table and the command line all read :func:`kind_specs`, so adding a kind is
one module (plus its test) and no table elsewhere.

:func:`kind_specs` is the one place backends are discovered: on first use it imports every module of the
``vlmproprio.backends`` package by name. The import is by name so that this early module (and
vlmproprio.models after it) need no import of a later stage; it is the only such import in the package. A
backend module therefore stays cheap to import: heavy libraries (torch, openai) are imported when a backend
is built or checked, never at module level.
"""

from __future__ import annotations

import importlib
import pkgutil
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from vlmproprio.errors import VlmproprioError

BACKENDS_PACKAGE = "vlmproprio.backends"


@dataclass(frozen=True)
class KindOption:
    """One command-line option of a backend kind and the setting it sets (argparse's dest comes from the flag)."""

    flag: str  # "--batch-size"
    setting: str  # the field of the kind's settings type it sets ("max_batch_size")
    helps: Mapping[str, str]  # command ("run", "models", "score") -> help text: the commands that take it
    type: Callable[[str], object] | None = None
    default: object = None
    action: str | None = None  # "store_true" for a switch

    @property
    def dest(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")

    def argparse_kwargs(self, command: str) -> dict:
        """What ``add_argument`` takes for this option in ``command`` (unset fields left to argparse)."""
        given = {"type": self.type, "default": self.default, "action": self.action}
        return {"help": self.helps[command], **{k: v for k, v in given.items() if v is not None}}


@dataclass(frozen=True)
class KindSpec:
    """One backend kind: what its model names look like, what it is set with, how it is built and checked.

    ``create(ref, settings)`` builds the backend and ``live(ref, settings)`` says, without loading weights,
    whether it can run here (an Availability); ``settings`` is the run's BackendSettings, whose
    ``for_kind(kind)`` is an instance of ``settings_type``.
    """

    kind: str  # ModelRef.kind, and the slug's first word ("hf" -> hf_<...>)
    create: Callable
    live: Callable
    prefix: str | None = None  # model names "<prefix><weights>"; None: only the registry's short names
    syntax: str = ""  # the name form an unknown-model message offers, "hf:<folder or HF repo id>"
    label: str = ""  # a prefixed name's description is "<weights> (<label>)"
    slug: Callable[[str, str], str] | None = None  # (name, weights) -> one safe path component
    settings_type: type | None = None  # a frozen dataclass; its field names are the kind's settings
    options: tuple[KindOption, ...] = ()
    option_group: str = ""  # the title of the kind's option group in the run command's help
    needs_cassette: bool = True  # False: rule-based, answers the same in every mode without a cassette


_REGISTERED: dict[str, KindSpec] = {}
_LOCK = threading.RLock()
_discovered = False


class KindError(VlmproprioError):
    """Two backend kinds that claim the same name or prefix."""


def register_kind(spec: KindSpec) -> KindSpec:
    """Declare a backend kind (called by its backend module when it is imported); returns ``spec``.

    The same kind registered again replaces the earlier spec (a module reloaded); a prefix another kind
    already claims is a KindError."""
    with _LOCK:
        for other in _REGISTERED.values():
            if other.kind != spec.kind and spec.prefix and other.prefix == spec.prefix:
                raise KindError(f"backend kinds {other.kind!r} and {spec.kind!r} both claim prefix {spec.prefix!r}")
        _REGISTERED[spec.kind] = spec
    return spec


def _discover() -> None:
    global _discovered
    with _LOCK:
        if _discovered:
            return
        package = importlib.import_module(BACKENDS_PACKAGE)
        for info in pkgutil.iter_modules(package.__path__):
            importlib.import_module(f"{BACKENDS_PACKAGE}.{info.name}")
        _discovered = True


def kind_specs() -> tuple[KindSpec, ...]:
    """Every registered backend kind, ordered by kind name (so settings records and option groups do not
    depend on which module happened to be imported first)."""
    _discover()
    with _LOCK:
        return tuple(sorted(_REGISTERED.values(), key=lambda s: s.kind))


def kind_spec(kind: str) -> KindSpec:
    """The spec of one kind; KindError if no backend module registers it."""
    for spec in kind_specs():
        if spec.kind == kind:
            return spec
    raise KindError(f"no backend module registers kind {kind!r}; known: {', '.join(s.kind for s in kind_specs())}")
