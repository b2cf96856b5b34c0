"""What a local transformers model is loaded from: its weights (a folder, the Hugging Face cache, or the Hub)
and its processor.

Offline only unless asked: weights come from a local folder or the local Hugging Face cache
(``local_files_only``); ``allow_download`` fetches a repo id missing from the cache.

Revision (the cache key's ``revision``): the snapshot commit hash when the model comes from the HF cache (a
commit covers every file of the repo), else ``sha256:<hex>`` over the bytes of every file of the folder
(``folder_revision``) but hidden files, documentation, bytecode and the tiny builds' stamp: the weights and
everything read beside them — config, generation config, processor and tokenizer files, chat template, any
code the folder ships. An edited chat template or preprocessor config is a new revision, so it never replays
answers cached under the old one; a local folder, such as a tiny test model, gets the same revision on every
machine. Files no loader reads (an ``onnx/`` export) are hashed too: slower, never wrong.

Without torchvision (it cannot be installed next to the CPU torch used here),
``AutoProcessor`` fails for processors that also declare a video processor
(Qwen2-VL, Qwen2.5-VL, Qwen3-VL, GLM-4V, InternVL, LLaVA-OneVision, SmolVLM2). The fallback loads the same processor
class without its video part: a local subclass whose sub-processor list leaves
``video_processor`` out, loaded with the ordinary ``from_pretrained``. Nothing
in transformers is patched. Images work exactly as with AutoProcessor; videos
are not supported (vlmproprio sends none): where the processor's code reads its
video processor's settings whatever it is given (SmolVLM's chat template call),
a stand-in answers None, and a video is refused.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import re
import types
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.backends.base import BackendError
from vlmproprio.digests import Listing, folder_digest
from vlmproprio.episodes import sha256_file
from vlmproprio.io import ReadError

WEIGHT_SUFFIXES = (".safetensors", ".bin")
_SNAPSHOT_RE = re.compile(r"models--(?P<org>[^/]+?)--(?P<name>[^/]+)/snapshots/(?P<commit>[0-9a-f]{40})/?$")
_HF_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*(/[A-Za-z0-9][A-Za-z0-9._-]*)?$")


@dataclass(frozen=True)
class ResolvedWeights:
    path: Path
    model_id: str
    revision: str
    source: str  # "hf-cache" | "local"


# Files that decide no answer: documentation, bytecode (its .py is hashed), and the tiny builds' stamp (its
# build number moves with the project's build code even when no file a model reads does). Hidden files and
# folders (.git, .cache) too. Everything else is hashed as the bytes transformers reads: a file that merely
# looks cosmetic can change answers (transformers reads the transformers_version a config.json was written by).
STAMP_FILE = "vlmproprio-tiny.json"  # what built a tiny model (vlmproprio.backends.tiny)
UNHASHED_NAMES = (STAMP_FILE,)
_DOCUMENTATION = re.compile(r"^(readme|license|licence|notice|copying)([._-].*)?$|\.md$", re.IGNORECASE)
_BYTECODE = ("__pycache__",)


def _deciding(rel: Path) -> bool:
    return not (
        any(part.startswith(".") or part in _BYTECODE for part in rel.parts)
        or rel.name in UNHASHED_NAMES
        or rel.suffix == ".pyc"
        or _DOCUMENTATION.search(rel.name)
    )


def _unreadable(path: Path, detail: str) -> BackendError:
    return BackendError(f"{path}: cannot hash this file of the model folder: {detail}")


def _revision_of(root: Path, listing: Listing) -> str:
    """sha256 over (relative POSIX path, sha256 of the bytes) of each listed file, in order."""
    h = hashlib.sha256()
    for rel, *_ in listing:
        path = root / rel
        try:
            digest = sha256_file(path)
        except ReadError as exc:
            raise _unreadable(path, getattr(exc, "detail", "") or str(exc)) from exc
        except OSError as exc:  # FileNotFoundError: removed while hashing
            raise _unreadable(path, exc.strerror or str(exc)) from exc
        h.update(f"{rel}\0{digest}\n".encode("utf-8", "surrogateescape"))  # any name a folder can hold
    return h.hexdigest()


def folder_revision(folder: Path, memo: Path | None = None) -> str:
    """The revision of a local model folder: ``_revision_of`` every file but those ``_deciding`` leaves out, in
    the order of their paths (the same on every platform). With ``memo`` (a folder), remembered there across
    processes while no file changes (vlmproprio.digests): a model's weights are gigabytes."""
    folder = Path(folder)
    try:
        found = [(p.relative_to(folder), p) for p in folder.rglob("*") if p.is_file()]
        files = sorted((rel.as_posix(), p) for rel, p in found if _deciding(rel))
        if not any(rel.endswith(WEIGHT_SUFFIXES) for rel, _ in files):
            raise BackendError(f"{folder}: no weight files (*.safetensors or *.bin)")
        if memo is not None:
            with contextlib.suppress(OSError):  # not remembered, still right
                Path(memo).mkdir(parents=True, exist_ok=True)
        digest = folder_digest(folder, [p for _, p in files], memo, hasher=_revision_of, name="model-revision")
    except OSError as exc:  # a folder that cannot be listed, a file gone before it was listed
        raise _unreadable(Path(exc.filename or folder), exc.strerror or str(exc)) from exc
    return "sha256:" + digest


def how_to_provide(repo_id: str) -> str:
    return (
        f"download it on a machine with network (`hf download {repo_id}`, or "
        f"`huggingface-cli download {repo_id}`) and copy the Hugging Face cache (~/.cache/huggingface/hub, "
        "or $HF_HUB_CACHE) here; or, where the Hub is reachable, add --allow-download; or pass a local folder as "
        "`hf:/path/to/folder`; or, without the model, "
        "replay its recorded answers (--mode replay with a cassette in fixtures/responses/)"
    )


def resolve_weights(
    weights: str | Path, model_id: str | None = None, *, allow_download: bool = False, memo: Path | None = None
) -> ResolvedWeights:
    """Find weights: a local folder, or an HF repo id in the local HF cache; with ``allow_download`` an id that
    is not there is fetched from the Hugging Face Hub (when one is reachable). ``memo``: where a local folder's
    revision may be remembered (see folder_revision)."""
    text = str(weights)
    path = Path(text).expanduser()
    if path.is_dir():
        path = path.resolve()
        m = _SNAPSHOT_RE.search(path.as_posix())
        if m:  # a folder inside the HF cache: the commit hash is the revision
            return ResolvedWeights(path, model_id or f"{m['org']}/{m['name']}", m["commit"], "hf-cache")
        return ResolvedWeights(path, model_id or path.name, folder_revision(path, memo), "local")
    if text.startswith(("/", ".", "~")) or not _HF_ID_RE.match(text):
        raise BackendError(f"model folder {text} does not exist")
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    try:
        snap = Path(snapshot_download(text, local_files_only=True))
    except (LocalEntryNotFoundError, FileNotFoundError, OSError) as exc:
        if allow_download:
            return _download_weights(text, model_id)
        raise BackendError(
            f"weights for {text} are not in the local Hugging Face cache and downloads are off; " + how_to_provide(text)
        ) from exc
    return ResolvedWeights(snap, model_id or text, snap.name, "hf-cache")


def _download_weights(repo_id: str, model_id: str | None) -> ResolvedWeights:
    """The weights of ``repo_id`` fetched from the Hub into the local HF cache (--allow-download)."""
    from huggingface_hub import snapshot_download

    try:
        snap = Path(snapshot_download(repo_id))
    except Exception as exc:  # offline, unknown repo, gated: all say "could not download", with the hub's reason
        raise BackendError(
            f"--allow-download: could not download {repo_id} from the Hugging Face Hub "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); " + how_to_provide(repo_id)
        ) from exc
    return ResolvedWeights(snap, model_id or repo_id, snap.name, "hf-cache")


def hf_weights_available(weights: str) -> tuple[bool, str]:
    """Whether ``weights`` (folder or HF id) can be loaded offline, and if not, how to get them."""
    try:
        r = resolve_weights(weights)
    except BackendError as exc:
        return False, str(exc)
    return True, f"{r.source}: {r.path}"


# ---------------------------------------------------------------------------------------------- processor


def _processor_class_name(path: Path) -> str | None:
    for name in ("processor_config.json", "preprocessor_config.json", "tokenizer_config.json"):
        try:
            data = json.loads((path / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict) and isinstance(data.get("processor_class"), str):
            return data["processor_class"]
    from transformers import AutoConfig
    from transformers.models.auto.processing_auto import PROCESSOR_MAPPING_NAMES

    config = AutoConfig.from_pretrained(path, local_files_only=True)
    return PROCESSOR_MAPPING_NAMES.get(config.model_type)


def _video_optional(init: types.FunctionType) -> types.FunctionType:
    """``init`` with None as the default of its ``video_processor`` parameter where that is the last required
    positional one (SmolVLM's processor requires it); any other ``init`` unchanged. The same code object:
    ``from_pretrained`` reads the parameter names off it to decide which saved settings to pass."""
    code = init.__code__
    names = code.co_varnames[: code.co_argcount]
    defaults = init.__defaults__ or ()
    first_default = code.co_argcount - len(defaults)
    if "video_processor" not in names or names.index("video_processor") != first_default - 1:
        return init
    copy = types.FunctionType(code, init.__globals__, init.__name__, (None, *defaults), init.__closure__)
    copy.__kwdefaults__ = init.__kwdefaults__
    copy.__qualname__, copy.__doc__, copy.__module__ = init.__qualname__, init.__doc__, init.__module__
    copy.__annotations__ = dict(getattr(init, "__annotations__", {}))
    return copy


class _NoVideoProcessor:
    """Stands where an image-only processor's video processor would be, for code that reads its settings
    whatever the request holds (SmolVLM's ``apply_chat_template`` passes its ``num_frames`` and ``fps`` on):
    every setting is None, and processing a video is refused."""

    def __getattr__(self, name: str) -> None:
        if name.startswith("__"):
            raise AttributeError(name)
        return None

    def __call__(self, *args, **kwargs):
        raise BackendError("videos need the video processor, which needs torchvision; vlmproprio sends images only")


@functools.cache
def _image_only(processor_cls: type) -> type:
    """``processor_cls`` without its video processor: ``from_pretrained`` then loads only image + text parts."""

    def get_attributes(cls) -> list[str]:
        return [a for a in super(sub, cls).get_attributes() if a != "video_processor"]

    body = {
        "get_attributes": classmethod(get_attributes),
        "__init__": _video_optional(processor_cls.__init__),
        "video_processor": _NoVideoProcessor(),
    }
    sub = type(f"{processor_cls.__name__}ImageOnly", (processor_cls,), body)
    return sub


def load_processor(path: Path):
    """The model's processor; without torchvision, the same class minus its video processor."""
    import transformers
    from transformers import AutoProcessor
    from transformers.utils import is_torchvision_available

    name = None if is_torchvision_available() else _processor_class_name(path)
    cls = getattr(transformers, name, None) if name else None
    if cls is None or "video_processor" not in cls.get_attributes():
        return AutoProcessor.from_pretrained(path, local_files_only=True), "AutoProcessor"
    return _image_only(cls).from_pretrained(path, local_files_only=True), f"{name} without video processor"
