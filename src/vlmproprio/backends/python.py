"""Your own model from Python: the ``py`` backend kind.

A model is any object that answers a :class:`~vlmproprio.chat.ChatRequest` (its ``messages``, each a role and
parts: :class:`~vlmproprio.chat.TextPart` ``.text`` and :class:`~vlmproprio.chat.ImagePart` ``.data``, the PNG
bytes of a frame; ``config`` holds the decoding settings) with its text:

* a :class:`~vlmproprio.backends.base.Backend` (its own ``identity()`` enters the cache key), or
* a callable ``request -> str``.

Two ways to name one:

* ``py:package.module:factory`` on the command line, the pytest benchmark and tox: ``factory()`` is imported and
  called once per run and returns the model. Its identity in the cache key is that name, plus the model's
  ``version`` attribute if it has one (change it when the weights change, so old answers are not served).
* :func:`register_python_model` from Python (what :func:`vlmproprio.evaluate` does): ``py:<name>`` for an
  object in this process, with the identity the caller names.

Answers are cached, recorded as cassettes and replayed exactly as any other kind's; replaying a cassette needs
neither the model nor its module.
"""

from __future__ import annotations

import importlib
import re
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from vlmproprio.backends.base import Availability, Backend, BackendError
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.kinds import KindSpec, register_kind
from vlmproprio.models import ModelRef, file_slug

if TYPE_CHECKING:
    from vlmproprio.backends.settings import BackendSettings

TARGET_RE = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")  # package.module:factory


@dataclass(frozen=True)
class PythonModel:
    """A model object and the identity its answers are cached under."""

    model: object
    revision: str = ""


_IN_PROCESS: dict[str, PythonModel] = {}
_LOCK = threading.Lock()


def register_python_model(name: str, model: object, *, revision: str = "") -> ModelRef:
    """Make ``model`` (a Backend or a callable ``request -> str``) the model ``py:<name>`` in this process.

    ``name`` and ``revision`` are its identity in the cache key: the same name and revision must mean the
    same answers, so change the revision when the model changes."""
    from vlmproprio.models import resolve_model

    if not callable(model) and not isinstance(model, Backend):
        raise BackendError(f"{_named(name)}: the model must be a vlmproprio Backend or a callable request -> str")
    if ":" in name or not name.strip():
        raise BackendError(f"{_named(name)}: a registered model's name has no ':' (that form imports a factory)")
    with _LOCK:
        _IN_PROCESS[name] = PythonModel(model, revision)
    return resolve_model(_named(name))


class CallableBackend(Backend):
    """A callable ``request -> str`` as a backend: one request per call, in order."""

    def __init__(self, fn: Callable[[ChatRequest], str], model_id: str, revision: str = "") -> None:
        self.fn = fn
        self.model_id = model_id
        self.revision = revision

    def identity(self) -> dict[str, str]:
        return {"backend": "py", "model_id": self.model_id, "revision": self.revision}

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        meta = AnswerMeta("py", self.model_id, self.revision)
        return [Answer(self._text(r), meta) for r in requests]

    def _text(self, request: ChatRequest) -> str:
        try:
            text = self.fn(request)
        except Exception as exc:  # the user's code: name it, keep its type, no traceback from our side
            raise BackendError(
                f"{_named(self.model_id)}: the model raised {type(exc).__name__}: {exc} ({request.tag})"
            ) from exc
        if not isinstance(text, str):
            raise BackendError(
                f"{_named(self.model_id)}: the model returned {type(text).__name__}, not str ({request.tag})"
            )
        return text


def _import_factory(target: str) -> Callable[[], object]:
    if not TARGET_RE.match(target):
        raise BackendError(f"{_named(target)}: expected py:package.module:factory, or a model registered from Python")
    module_name, attr = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise BackendError(
            f"{_named(target)}: cannot import {module_name} ({exc}); is it installed or on PYTHONPATH?"
        ) from exc
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise BackendError(f"{_named(target)}: {module_name} has no callable {attr}")
    return factory


def _backend_of(model: object, model_id: str, revision: str) -> Backend:
    if isinstance(model, Backend):
        return model
    if callable(model):
        return CallableBackend(model, model_id, revision)
    raise BackendError(
        f"{_named(model_id)}: got {type(model).__name__}; expected a Backend or a callable request -> str"
    )


def _create(ref: ModelRef, settings: BackendSettings) -> Backend:
    registered = _IN_PROCESS.get(ref.weights)
    if registered is not None:
        return _backend_of(registered.model, ref.weights, registered.revision)
    factory = _import_factory(ref.weights)
    try:
        model = factory()
    except Exception as exc:
        raise BackendError(f"{_named(ref.weights)}: the factory raised {type(exc).__name__}: {exc}") from exc
    return _backend_of(model, ref.weights, str(getattr(model, "version", "") or ""))


def _live(ref: ModelRef, settings: BackendSettings) -> Availability:
    if ref.weights in _IN_PROCESS:
        return Availability(True, "a model registered in this process")
    try:
        _import_factory(ref.weights)
    except BackendError as exc:
        return Availability(False, str(exc))
    return Availability(True, f"the factory {ref.weights}")


def _slug(name: str, target: str) -> str:
    return file_slug(name, "py", target, target.replace(":", "_"), lossless=False)


def _named(target: str) -> str:
    """The model name of a target, as messages spell it: the kind's prefix and the target."""
    return f"{_SPEC.prefix}{target}"


_SPEC = register_kind(
    KindSpec(
        kind="py",
        create=_create,
        live=_live,
        prefix="py:",
        syntax="py:<package.module:factory>",
        label="Python model",
        slug=_slug,
    )
)
