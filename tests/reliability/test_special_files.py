"""Issue 36, items 11, 13 and 14: special files, the JSON reader's error paths, damaged arrays, images and URLs.

Every file the suite reads or writes by a path a user gave is a regular file of bounded size: a device, FIFO or
folder is refused in one line naming it (``cassette import /dev/zero`` read until the process was killed at
24 GB; ``cassette export --out /dev/full`` read it too, to merge). The JSON reader's size and read-error paths
carry ``detail`` like its other errors (an ``episode.json`` that is a folder, a manifest over the size limit
gave an AttributeError). A ``steps.npz`` of strings, a PNG frame claiming 16000 x 16000 pixels and a server URL
with port 99999 are one line each, naming the file or the flag.

The CLI runs as a process of its own, its address space capped at 4 GB by a prelude: reading a device without
limit then ends in a MemoryError traceback rather than in swapping the machine.
"""

from __future__ import annotations

import io
import os
import shutil
import stat
import zipfile
from pathlib import Path

import numpy as np
import pytest
from reliability_support import assert_argparse_error, assert_one_line_error, cli, cli_env, fixture_subset

from vlmproprio.episodes import write_manifest

CAPPED = "import resource\nresource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))"
RUN = ("--model", "reference", "--episodes", "door_00", "--conditions", "none", "--no-progress")


def capped_cli(args, **kw):
    return cli([str(a) for a in args], python_prelude=CAPPED, timeout=90, **kw)


@pytest.fixture(scope="module")
def answered(tmp_path_factory) -> Path:
    """A cache folder holding the reference model's answers for one episode (what `cassette export` exports)."""
    root = tmp_path_factory.mktemp("special")
    fixtures = fixture_subset(root / "fixtures", ["door_00"])
    proc = cli(["run", *RUN, "--fixtures", fixtures, "--out", root / "run", "--cache-dir", root / "cache"])
    assert proc.returncode == 0, proc.stderr
    return root / "cache"


@pytest.fixture
def fifo(tmp_path) -> Path:
    path = tmp_path / "pipe.jsonl"
    os.mkfifo(path)
    return path


# ---------------------------------------------------------------------------------------------- item 11

SPECIAL = {
    "import /dev/zero": (["cassette", "import", "/dev/zero"], "/dev/zero: a character device"),
    "import a FIFO": (["cassette", "import", "{fifo}"], "pipe.jsonl: a FIFO"),
    "import a folder": (["cassette", "import", "{tmp}"], "a folder, not a regular file"),
    "export to /dev/full": (["cassette", "export", "--model", "reference", "--out", "/dev/full"], "/dev/full: a"),
    "export to /dev/full, replacing": (
        ["cassette", "export", "--model", "reference", "--out", "/dev/full", "--replace"],
        "cannot write /dev/full: a character device",
    ),
    "export to a FIFO, replacing": (
        ["cassette", "export", "--model", "reference", "--out", "{fifo}", "--replace"],
        "pipe.jsonl: a FIFO (named pipe), not a regular file",
    ),
}


@pytest.mark.parametrize("case", list(SPECIAL))
def test_devices_fifos_and_folders_are_refused_not_read_or_written(answered, tmp_path, fifo, case, figures):
    argv, message = SPECIAL[case]
    argv = [a.format(fifo=fifo, tmp=tmp_path) for a in argv]
    proc = capped_cli([*argv, "--cache-dir", answered, *(["--no-embed"] if "export" in argv else [])])
    assert_one_line_error(proc, message, "not a regular file")
    assert stat.S_ISFIFO(fifo.stat().st_mode) and stat.S_ISCHR(os.stat("/dev/full").st_mode)  # left as they were
    figures("special files refused (issue 36: 11)", cases=1, one_line_errors=1, read_or_written=0)


# ---------------------------------------------------------------------------------------------- item 13


@pytest.fixture
def fixtures(tmp_path) -> Path:
    return fixture_subset(tmp_path / "fixtures", ["door_00"])


def _episode_json_a_folder(fx: Path) -> None:
    path = fx / "episodes/door_00/episode.json"
    path.unlink()
    path.mkdir()
    (path / "inside.txt").write_text("a file, so the regenerated manifest lists the folder's content\n")
    write_manifest(fx)


def _manifest_over_the_limit(fx: Path) -> None:
    with open(fx / "manifest.json", "r+b") as f:  # sparse: 300 MB by its size, nothing on the disk
        f.truncate(300 << 20)


def _steps_a_folder(fx: Path) -> None:
    path = fx / "episodes/door_00/steps.npz"
    path.unlink()
    path.mkdir()
    (path / "inside.txt").write_text("x\n")
    write_manifest(fx)


JSON_ERRORS = {
    "episode.json is a folder": (_episode_json_a_folder, "run", "episode.json: cannot read episode metadata (a folder"),
    "manifest over the size limit": (_manifest_over_the_limit, "verify", "not a valid manifest (314,572,800 bytes"),
    "manifest over the size limit (run)": (_manifest_over_the_limit, "run", "manifest.json: not a valid manifest"),
    "steps.npz is a folder": (_steps_a_folder, "verify", "steps.npz: cannot read full-rate states (a folder"),
}


@pytest.mark.parametrize("case", list(JSON_ERRORS))
def test_read_errors_of_fixture_files_are_one_line(fixtures, tmp_path, case, figures):
    damage, command, message = JSON_ERRORS[case]
    damage(fixtures)
    args = [command, "--fixtures", fixtures] + (
        [*RUN, "--out", tmp_path / "run", "--cache-dir", tmp_path / "c"] if command == "run" else []
    )
    assert_one_line_error(capped_cli(args), message)
    figures("read errors of fixture files (issue 36: 13)", cases=1, one_line_errors=1, tracebacks=0)


# ---------------------------------------------------------------------------------------------- item 14


def _rewrite_steps(fx: Path, name: str, convert) -> None:
    path = fx / "episodes/door_00/steps.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays[name] = convert(arrays[name])
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    write_manifest(fx)


def _bomb_frame(fx: Path) -> None:
    from PIL import Image

    # a bilevel image: 32 MB to make, a few KB as a PNG, 256 million pixels (PIL refuses past ~179 million)
    Image.new("1", (16000, 16000)).save(fx / "episodes/door_00/frames/000.png", format="PNG")
    write_manifest(fx)


DAMAGED = {
    "joints as strings": (lambda fx: _rewrite_steps(fx, "joints", lambda a: a.astype(str)), "joints holds <U"),
    "step as bytes": (lambda fx: _rewrite_steps(fx, "step", lambda a: a.astype("S8")), "step holds |S8"),
    "phase as strings": (lambda fx: _rewrite_steps(fx, "phase", lambda a: a.astype(str)), "phase holds <U"),
    "ee as complex numbers": (lambda fx: _rewrite_steps(fx, "ee", lambda a: a.astype(complex)), "ee holds complex"),
    "a 16000x16000 frame": (_bomb_frame, "frames/000.png: image too large to decode"),
}


@pytest.mark.parametrize("command", ["run", "verify"])
@pytest.mark.parametrize("case", list(DAMAGED))
def test_damaged_arrays_and_images_are_one_line_naming_the_file(fixtures, tmp_path, case, command, figures):
    damage, message = DAMAGED[case]
    damage(fixtures)
    args = [command, "--fixtures", fixtures] + (
        [*RUN, "--out", tmp_path / "run", "--cache-dir", tmp_path / "c"] if command == "run" else []
    )
    assert_one_line_error(capped_cli(args), message)
    figures("damaged arrays and images (issue 36: 14)", cases=1, one_line_errors=1, tracebacks=0)


BAD_URLS = {
    "port 99999": "http://127.0.0.1:99999/v1",
    "port not a number": "http://127.0.0.1:8o00/v1",
    "no host": "http:///v1",
    "not http": "file:///etc/passwd",
    "broken IPv6": "http://[::1/v1",
}


@pytest.mark.parametrize("command", ["run", "models", "score"])
@pytest.mark.parametrize("case", list(BAD_URLS))
def test_unusable_base_urls_are_a_usage_error_naming_the_flag(tmp_path, case, command, figures):
    args = {"run": ["run", "--model", "openai:m"], "models": ["models"], "score": ["score", tmp_path]}[command]
    proc = cli([*map(str, args), "--base-url", BAD_URLS[case]], cwd=tmp_path)
    assert_argparse_error(proc, "--base-url")
    figures("unusable server URLs (issue 36: 14)", cases=1, usage_errors=1, tracebacks=0)


def test_an_unusable_openai_base_url_variable_is_one_line_naming_it(fixtures, tmp_path, figures):
    env = cli_env(OPENAI_BASE_URL="http://127.0.0.1:99999/v1", OPENAI_API_KEY="sk-test-0123456789")
    args = ["run", "--fixtures", fixtures, *RUN, "--model", "openai:m", "--out", tmp_path / "run"]
    proc = cli([*map(str, args), "--cache-dir", str(tmp_path / "c")], env=env)
    assert_one_line_error(proc, "$OPENAI_BASE_URL", "Port out of range")
    figures("unusable server URLs (issue 36: 14)", cases=1, usage_errors=1, tracebacks=0)


def test_a_damaged_sidecar_is_named_by_its_file(tmp_path, figures):
    """A flipped flag bit marks a member encrypted: zipfile raised a RuntimeError naming ``header.npy``, and
    the score ended in its traceback."""
    fixtures = fixture_subset(tmp_path / "fixtures", ["door_00"])
    sidecar = fixtures / "responses" / "reference.embeddings.npz"
    sidecar.parent.mkdir()
    data = bytearray((Path(__file__).parents[2] / "fixtures/responses/reference.embeddings.npz").read_bytes())
    entry = data.find(b"PK\x01\x02")  # the first member's entry in the central directory, which zipfile believes
    data[entry + 8] |= 0x01  # its "encrypted" flag (general purpose bit 0)
    sidecar.write_bytes(bytes(data))
    with zipfile.ZipFile(sidecar) as zf:
        assert zf.infolist()[0].filename == "header.npy"
    write_manifest(fixtures)
    run = tmp_path / "run"
    proc = cli(["run", "--fixtures", str(fixtures), *RUN, "--out", str(run), "--cache-dir", str(tmp_path / "c")])
    assert proc.returncode == 0, proc.stderr
    line = assert_one_line_error(cli(["score", str(run), "--cache-dir", str(tmp_path / "c")]), str(sidecar))
    assert line.index(str(sidecar)) < line.find("header.npy") or "header.npy" not in line
    shutil.rmtree(run)
    figures("damaged sidecars (issue 36: 17)", cases=1, named_by_file=1)


def _json_over(path: Path) -> Path:
    path.write_text("{}")
    with open(path, "r+b") as f:
        f.truncate(300 << 20)  # sparse: the size, not the bytes
    return path


def _json_folder(path: Path) -> Path:
    path.mkdir()
    return path


def _json_fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


@pytest.mark.parametrize(
    ("make", "detail"),
    [(_json_over, "314,572,800 bytes, more than"), (_json_folder, "a folder"), (_json_fifo, "a FIFO")],
    ids=["over the limit", "a folder", "a FIFO"],
)
def test_every_error_of_the_json_reader_has_detail(tmp_path, make, detail):
    """The callers phrase their own line from ``detail`` (load_episode, read_manifest): every path has it."""
    from vlmproprio.io import JSONLoadError, load_json, load_required_json

    path = make(tmp_path / "doc.json")
    with pytest.raises(JSONLoadError) as caught:
        load_json(path)
    assert detail in caught.value.detail and str(caught.value) == f"{path}: {caught.value.detail}"
    with pytest.raises(JSONLoadError) as caught:
        load_required_json(tmp_path / "absent.json", "absent.json is missing: run X")
    assert caught.value.detail == "absent.json is missing: run X"


@pytest.mark.parametrize("command", ["manifest", "verify", "run"])
def test_a_fifo_among_the_fixture_files_is_named_by_every_command(fixtures, tmp_path, command, figures):
    frame = fixtures / "episodes/door_00/frames/001.png"
    frame.unlink()
    os.mkfifo(frame)  # opened for reading, it would wait for a writer forever
    args = [command, "--fixtures", fixtures]
    if command == "run":
        args += [*RUN, "--out", tmp_path / "run", "--cache-dir", tmp_path / "c"]
    assert_one_line_error(capped_cli(args), f"{frame}: a FIFO (named pipe) inside the fixture folder")
    figures("special files refused (issue 36: 11)", cases=1, one_line_errors=1, read_or_written=0)
