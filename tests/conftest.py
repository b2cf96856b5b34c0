"""Shared fixtures: offline, single-threaded, a tiny Qwen2-VL checkpoint per session, request builders."""

from __future__ import annotations

import atexit
import io
import os
import shutil
import tempfile
from pathlib import Path

# Before anything imports torch or huggingface_hub: no network, one thread (bit-identical floats).
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
# Tests never read or write a developer's caches (responses, embeddings, tiny models built elsewhere). Each test
# process (each xdist worker) has its own cache root: diskcache's SQLite database shared by concurrent workers
# can be left malformed.


def _remove_if_owner(owner: int, root: str) -> None:
    """At exit, not at pytest_sessionfinish: a run that stops on a usage error never finishes a session. Only in
    the process that made the root: a child forked from it inherits the handler."""
    if os.getpid() == owner:
        shutil.rmtree(root, ignore_errors=True)


os.environ["VLMPROPRIO_CACHE"] = tempfile.mkdtemp(prefix="vlmproprio-test-cache-")
atexit.register(_remove_if_owner, os.getpid(), os.environ["VLMPROPRIO_CACHE"])

# (imports after the environment is set up: E402)
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart, Message, RequestTag, TextPart  # noqa: E402

SESSION_CACHE = Path(os.environ["VLMPROPRIO_CACHE"])


def png_bytes(seed: int, size: int = 64) -> bytes:
    """A deterministic random RGB PNG."""
    from PIL import Image

    rgb = np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def make_request(
    text: str = "# Process 1\nDescribe the frames.",
    images: tuple[bytes, ...] = (),
    *,
    system: str | None = None,
    config: GenerationConfig | None = None,
    prompt_version: str = "test-1",
    tag: RequestTag | None = None,
) -> ChatRequest:
    messages = []
    if system is not None:
        messages.append(Message("system", (TextPart(system),)))
    messages.append(Message("user", (*tuple(ImagePart(b) for b in images), TextPart(text))))
    return ChatRequest(
        messages=tuple(messages),
        config=config or GenerationConfig(max_new_tokens=8),
        prompt_version=prompt_version,
        tag=tag or RequestTag("door_00", "both", "p1", 0),
    )


@pytest.fixture
def request_factory():
    return make_request


@pytest.fixture
def png_factory():
    return png_bytes


@pytest.fixture(scope="session")
def torch_one_thread():
    torch = pytest.importorskip("torch", reason="the hf backend needs torch (pip install 'vlmproprio[hf]')")
    torch.set_num_threads(1)
    return torch


@pytest.fixture(scope="session", autouse=True)
def _tiny_models_shared_by_the_workers(tmp_path_factory):
    """Under pytest-xdist, each worker's cache root gets its models/ folder as a link to one folder of the whole
    session (beside the workers' own temporary folders), so a tiny checkpoint (~5 CPU s) is built once per session
    rather than once per worker. Safe where the whole cache root is not (its SQLite databases): a build is plain
    files made in a temporary folder and renamed into place, and a worker that loses the race uses the winner's
    (vlmproprio.backends.tiny.ensure_tiny_model). Nothing else in the cache root is shared."""
    link = SESSION_CACHE / "models"
    if os.environ.get("PYTEST_XDIST_WORKER") and not link.exists():
        shared = tmp_path_factory.getbasetemp().parent / "tiny-models"
        shared.mkdir(exist_ok=True)
        link.symlink_to(shared, target_is_directory=True)


@pytest.fixture(scope="session")
def tiny_model(torch_one_thread):
    """The tiny random checkpoint of a family (about 1 MB), built once per test session in the session's cache
    root ($VLMPROPRIO_CACHE/models, shared by the xdist workers), where the registry's ``tiny-*`` models look for
    it: a test that runs ``tiny-qwen2-vl`` by name and asks for this fixture finds the build instead of making
    its own."""
    from filelock import FileLock

    from vlmproprio.backends.tiny import ensure_tiny_model

    def build(family: str) -> Path:
        # the workers start their tiny-model modules at about the same time: one builds, the others wait for it
        # (a race of builds would be safe, but each would cost the ~5 CPU s that sharing saves)
        (SESSION_CACHE / "models").mkdir(exist_ok=True)
        with FileLock(SESSION_CACHE / "models" / f".{family}.lock"):
            return ensure_tiny_model(family, SESSION_CACHE)

    return build


@pytest.fixture(scope="session")
def tiny_qwen2vl_dir(tiny_model):
    """The tiny random Qwen2-VL checkpoint (``tiny-qwen2-vl``), built once per test session."""
    return tiny_model("qwen2-vl")


@pytest.fixture(scope="session")
def tiny_qwen2vl_backend(tiny_qwen2vl_dir):
    from vlmproprio.backends.hf import HFBackend

    backend = HFBackend(tiny_qwen2vl_dir, model_id="tiny-qwen2-vl", device="cpu", dtype="float32", threads=1)
    backend.load()
    return backend


@pytest.fixture
def vlmproprio_home(tmp_path, monkeypatch):
    """A private cache root ($VLMPROPRIO_CACHE) so registry tiny models are built in a temp folder (models/)."""
    home = tmp_path / "home"
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(home))
    return home


def pytest_collection_modifyitems(config, items) -> None:
    """Modules with a slow test first (stable otherwise): under xdist (``--dist loadscope``) each module goes to
    one worker in this order, so the long ones start at once instead of being left for the end."""
    slow_modules = {item.module.__name__ for item in items if item.get_closest_marker("slow") and item.module}
    items.sort(key=lambda item: 0 if item.module and item.module.__name__ in slow_modules else 1)
