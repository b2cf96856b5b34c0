"""Issue 15, defects 6-8: output and caches inside the fixtures; cassettes and episodes that pass a regenerated
or edited manifest.

* ``--out``, ``--cache-dir``, ``--embedding-cache``, ``report --out`` inside the fixture folder (and the
  fixtures inside ``--out``) are refused in one line, before anything is written.
* Replay checks the cassette against the manifest: a line edited and re-checksummed (so the cassette itself
  reads fine) is refused, naming the file and the manifest.
* With the manifest regenerated after the damage (so every checksum passes), a flipped pixel, two swapped
  frames and a steps.npz from another episode are still caught when the episode is used.

The CLI runs in this process (``cli_in_process``): what is checked is its one error line and the files, not
the process, and a subprocess cost ~1.5 CPU s of imports per command (~10 s for one that scores).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from fault_support import cli_in_process
from reliability_support import assert_one_line_error, cache_env_sharing_embeddings, fixture_subset, tree_snapshot

from vlmproprio.cache import canonical_json, checksum
from vlmproprio.episodes import EpisodeError, load_episode, write_manifest

RUN_ARGS = ("--model", "reference", "--episodes", "door_00", "--conditions", "none", "--frame-stride", "3")


@pytest.fixture
def fixtures(tmp_path):
    return fixture_subset(tmp_path / "fixtures", ["door_00", "door_01"])


def _cache_env(tmp_path: Path) -> dict[str, str]:
    return {"VLMPROPRIO_CACHE": str(tmp_path / "cache")}


@pytest.mark.parametrize(
    "where",
    ["--out inside", "--cache-dir inside", "fixtures inside --out", "score --embedding-cache", "report --out"],
)
def test_output_and_caches_inside_the_fixtures_are_refused(tmp_path, tmp_path_factory, fixtures, where, figures):
    env = _cache_env(tmp_path)
    if where.startswith("score") or where.startswith("report"):
        # report scores the run before it meets --out: the session's shared embeddings spare it the encoder
        env = {"VLMPROPRIO_CACHE": cache_env_sharing_embeddings(tmp_path, tmp_path_factory)["VLMPROPRIO_CACHE"]}
        run = ["run", *RUN_ARGS, "--fixtures", fixtures, "--out", tmp_path / "run", "--no-progress"]
        proc = cli_in_process(run, env=env)
        assert proc.returncode == 0, proc.stderr
    before = tree_snapshot(fixtures)
    args = {
        "--out inside": ["run", *RUN_ARGS, "--fixtures", fixtures, "--out", fixtures / "runs" / "x"],
        "--cache-dir inside": [
            *("run", *RUN_ARGS, "--fixtures", fixtures, "--out", tmp_path / "run2"),
            *("--cache-dir", fixtures / "cache"),
        ],
        "fixtures inside --out": ["run", *RUN_ARGS, "--fixtures", fixtures, "--out", tmp_path],
        "score --embedding-cache": ["score", tmp_path / "run", "--embedding-cache", fixtures / "emb"],
        "report --out": ["report", tmp_path / "run", "--out", fixtures / "report"],
    }[where]
    proc = cli_in_process(args, env=env)
    assert_one_line_error(proc, str(fixtures))
    assert tree_snapshot(fixtures) == before
    assert cli_in_process(["verify", "--fixtures", fixtures], env=env).returncode == 0  # later runs still work
    figures("folders inside the fixtures", cases=1, refused=1, fixture_files_touched=0)


def test_replay_refuses_a_cassette_edited_and_rechecksummed(tmp_path, fixtures, figures):
    env = _cache_env(tmp_path)
    shutil.copy(Path(__file__).resolve().parents[2] / "fixtures" / "responses" / "tiny-qwen2-vl.jsonl", tmp_path)
    cassette = fixtures / "responses" / "tiny-qwen2-vl.jsonl"
    cassette.parent.mkdir()
    shutil.copy(tmp_path / "tiny-qwen2-vl.jsonl", cassette)
    write_manifest(fixtures)
    lines = cassette.read_text().splitlines()
    rec = json.loads(lines[1])
    rec["text"] = "Frame 1: the door is already open."  # a different answer, with a valid checksum
    rec["checksum"] = checksum(rec)
    lines[1] = canonical_json(rec)
    cassette.write_text("\n".join(lines) + "\n")
    args = ["run", "--model", "tiny-qwen2-vl", "--mode", "replay", *RUN_ARGS[2:], "--fixtures", fixtures]
    proc = cli_in_process([*args, "--out", tmp_path / "run", "--no-progress"], env=env)
    assert_one_line_error(proc, str(cassette.resolve()), "manifest.json")
    assert not (tmp_path / "run" / "transcripts").exists()
    figures("cassette vs manifest", edited_lines=1, refused=1)


def _swap_frames(ep_dir: Path) -> None:
    a, b = ep_dir / "frames" / "000.png", ep_dir / "frames" / "001.png"
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)


def _flip_pixel(ep_dir: Path) -> None:
    from PIL import Image

    path = ep_dir / "frames" / "000.png"  # a frame the run sends (every 3rd from 0)
    rgb = np.asarray(Image.open(path).convert("RGB")).copy()
    rgb[10, 10, 0] ^= 1
    Image.fromarray(rgb, "RGB").save(path, format="PNG")


def _other_steps(ep_dir: Path) -> None:
    shutil.copy(ep_dir.parent / "door_01" / "steps.npz", ep_dir / "steps.npz")


@pytest.mark.parametrize("damage", [_swap_frames, _flip_pixel, _other_steps], ids=["swap", "pixel", "steps"])
def test_damage_behind_a_regenerated_manifest_is_caught(tmp_path, fixtures, damage, figures):
    ep_dir = fixtures / "episodes" / "door_00"
    damage(ep_dir)
    write_manifest(fixtures)  # every checksum passes now
    env = _cache_env(tmp_path)
    run = ["run", *RUN_ARGS, "--fixtures", fixtures, "--out", tmp_path / "run", "--no-progress"]
    assert_one_line_error(cli_in_process(run, env=env), str(ep_dir))
    assert_one_line_error(cli_in_process(["verify", "--fixtures", fixtures], env=env), str(ep_dir))  # checks it all
    with pytest.raises(EpisodeError):
        ep = load_episode(fixtures, "door_00")
        for f in ep.frames:
            f.image_bytes()
    figures("damage behind a regenerated manifest", cases=1, caught=1)
