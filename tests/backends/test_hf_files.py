"""A local model folder's revision: every file that decides an answer, and nothing that does not."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vlmproprio.backends.base import BackendError
from vlmproprio.backends.hf_files import STAMP_FILE, folder_revision, resolve_weights


def _model(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "model.safetensors").write_bytes(b"\x00weights")
    (folder / "config.json").write_text(json.dumps({"model_type": "x", "transformers_version": "5.25.0"}))
    (folder / "preprocessor_config.json").write_text(json.dumps({"max_pixels": 65536, "min_pixels": 3136}))
    (folder / "tokenizer.json").write_text('{"model": {"vocab": {"a": 0}}}')
    (folder / "chat_template.jinja").write_text("{% for m in messages %}{{ m.content }}{% endfor %}")
    return folder


@pytest.mark.parametrize(
    ("name", "edit"),
    [
        ("chat_template.jinja", lambda t: t + "<|assistant|>"),
        ("preprocessor_config.json", lambda t: t.replace("65536", "262144")),
        ("tokenizer.json", lambda t: t.replace('"a": 0', '"b": 0')),
        ("config.json", lambda t: t.replace('"x"', '"y"')),
        ("model.safetensors", lambda t: t + "!"),
    ],
)
def test_every_file_a_model_reads_is_in_its_revision(tmp_path, name, edit):
    folder = _model(tmp_path / "m")
    before = folder_revision(folder)
    path = folder / name
    path.write_text(edit(path.read_text(errors="surrogateescape")), errors="surrogateescape")
    assert folder_revision(folder) != before


def test_a_new_file_beside_the_weights_is_a_new_revision(tmp_path):
    folder = _model(tmp_path / "m")
    before = folder_revision(folder)
    (folder / "processing_custom.py").write_text("class P: ...\n")  # a custom processor's code
    assert folder_revision(folder) != before


def test_what_decides_no_answer_keeps_the_revision(tmp_path):
    folder = _model(tmp_path / "m")
    before = folder_revision(folder)
    (folder / "README.md").write_text("# a model card\n")
    (folder / "LICENSE").write_text("Apache-2.0\n")
    (folder / ".gitattributes").write_text("*.safetensors filter=lfs\n")
    (folder / ".cache" / "huggingface").mkdir(parents=True)
    (folder / ".cache" / "huggingface" / "download.lock").write_text("")
    (folder / "__pycache__").mkdir()
    (folder / "__pycache__" / "processing_custom.cpython-311.pyc").write_bytes(b"\x00bytecode")
    (folder / STAMP_FILE).write_text('{"build_version": 99}\n')
    assert folder_revision(folder) == before


def test_a_config_saved_by_another_transformers_is_a_new_revision(tmp_path):
    """transformers reads the version a config.json was written by (a Mistral tokenizer's regex depends on it),
    so no byte of a config is taken for cosmetic."""
    folder = _model(tmp_path / "m")
    before = folder_revision(folder)
    config = json.loads((folder / "config.json").read_text())
    config["transformers_version"] = "4.57.0"
    (folder / "config.json").write_text(json.dumps(config))
    assert folder_revision(folder) != before


def test_files_in_subfolders_count_by_their_path(tmp_path):
    folder = _model(tmp_path / "m")
    (folder / "sub").mkdir()
    (folder / "sub" / "extra.json").write_text("{}")
    nested = folder_revision(folder)
    (folder / "sub" / "extra.json").rename(folder / "extra.json")
    assert folder_revision(folder) != nested
    (folder / "sub" / "extra.json").write_text("{}")  # both, and a name no UTF-8 decoder accepts
    (folder / "sub" / b"caf\xe9.json".decode("utf-8", "surrogateescape")).write_text("{}")
    assert folder_revision(folder).startswith("sha256:")


def test_the_revision_is_the_same_on_every_machine(tmp_path):
    assert folder_revision(_model(tmp_path / "a")) == folder_revision(_model(tmp_path / "b"))
    assert resolve_weights(tmp_path / "a").revision == folder_revision(tmp_path / "b")


def test_a_folder_without_weights_is_refused(tmp_path):
    folder = _model(tmp_path / "m")
    (folder / "model.safetensors").unlink()
    with pytest.raises(BackendError, match=r"no weight files"):
        folder_revision(folder)


def test_a_required_video_processor_is_made_optional_with_the_same_parameters():
    from vlmproprio.backends.hf_files import _video_optional

    class Processor:  # SmolVLMProcessor's signature: a video processor is required
        def __init__(self, image_processor, tokenizer, video_processor, image_seq_len=169, chat_template=None):
            self.parts = (image_processor, tokenizer, video_processor, image_seq_len, chat_template)

    init = _video_optional(Processor.__init__)
    # from_pretrained picks the saved settings it passes by these names: image_seq_len must stay one of them
    assert init.__code__ is Processor.__init__.__code__
    made = Processor.__new__(Processor)
    init(made, "ip", "tok", image_seq_len=64)
    assert made.parts == ("ip", "tok", None, 64, None)

    class Optional:
        def __init__(self, image_processor=None, video_processor=None): ...

    assert _video_optional(Optional.__init__) is Optional.__init__

    class Before:  # a required parameter after it: defaulting only the video processor is not possible
        def __init__(self, image_processor, video_processor, tokenizer): ...

    assert _video_optional(Before.__init__) is Before.__init__


def test_the_stand_in_video_processor_answers_none_and_refuses_videos():
    from vlmproprio.backends.hf_files import _NoVideoProcessor

    stand_in = _NoVideoProcessor()
    assert stand_in.num_frames is None and stand_in.fps is None
    with pytest.raises(BackendError, match=r"videos need the video processor, which needs torchvision"):
        stand_in(["a video"])


def test_an_unreadable_file_of_the_folder_is_one_clear_error(tmp_path, monkeypatch):
    import errno
    import os

    folder = _model(tmp_path / "m")
    target = str(folder / "tokenizer.json")
    real_open = os.open

    def open_(path, *args, **kwargs):  # as a file without read permission is, for a user other than root
        if str(path) == target:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", open_)
    with pytest.raises(BackendError) as caught:
        folder_revision(folder)
    assert (
        str(caught.value)
        == f"{target}: cannot hash this file of the model folder: cannot read (Permission denied (EACCES))"
    )


def test_a_folders_revision_is_remembered_until_a_file_changes(tmp_path, monkeypatch):
    """Hashed once for all processes that share the memo (a model's weights are gigabytes), and again as soon as
    any file changes; the encoder's digest of the same folder is remembered beside it, not in its place."""
    from vlmproprio import digests
    from vlmproprio.backends import hf_files

    monkeypatch.setattr(digests, "SETTLED_NS", 0)  # the files were written just now
    folder, memo = _model(tmp_path / "m"), tmp_path / "cache" / "models"
    plain = folder_revision(folder)
    hashed: list[str] = []
    real = hf_files.sha256_file
    monkeypatch.setattr(hf_files, "sha256_file", lambda p: hashed.append(p.name) or real(p))

    digests._digest.cache_clear()  # a new process
    assert folder_revision(folder, memo) == plain and "model.safetensors" in hashed
    hashed.clear()
    digests._digest.cache_clear()
    assert folder_revision(folder, memo) == plain and hashed == []  # from the memo
    assert digests.folder_digest(folder, [folder / "config.json"], memo) != plain.removeprefix("sha256:")
    assert folder_revision(folder, memo) == plain and hashed == []

    (folder / "chat_template.jinja").write_text("{{ messages }}")
    digests._digest.cache_clear()
    changed = folder_revision(folder, memo)
    assert changed != plain and changed == folder_revision(folder) and hashed
