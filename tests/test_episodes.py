"""The episode format: round trip, manifest verification, and clear errors for every kind of damage."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from vlmproprio import episodes as E


def _synthetic(root: Path, episode_id: str = "door_00", n_frames: int = 4) -> Path:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (16, 16, 3), dtype=np.uint8) for _ in range(n_frames)]
    steps = (n_frames - 1) * 20
    phases = ["approach"] * (steps // 2) + ["grasp handle"] * (steps - steps // 2 + 1)
    joints = rng.normal(size=(steps + 1, 8))
    ee = rng.normal(size=(steps + 1, 6))
    rows = [
        {
            "index": i,
            "step": 20 * i,
            "file": f"frames/{i:03d}.png",
            "pixel_sha256": E.pixel_sha256(images[i]),
            "joints": joints[20 * i].tolist(),
            "ee": ee[20 * i].tolist(),
            "phase": phases[20 * i],
            "direction": "still",
        }
        for i in range(n_frames)
    ]
    meta = E.episode_metadata(
        episode_id=episode_id,
        task="door",
        env_name="Door",
        target_object="door handle",
        action="open the door",
        instruction="Open the door.",
        target_bin=None,
        seed=0,
        steps=steps,
        stride=20,
        camera="sideview",
        image_size=(16, 16),
        versions={"robosuite": "1.5.2", "mujoco": "3.3.7"},
        success=True,
        phase_names=["approach", "grasp handle"],
        direction_vocab=["still"],
        phases=[E.PhaseSpan("approach", 0, steps // 2 - 1), E.PhaseSpan("grasp handle", steps // 2, steps)],
        frame_rows=rows,
    )
    states = E.StepStates(
        step=np.arange(steps + 1, dtype=np.int32),
        joints=joints,
        ee=ee,
        phase=np.array([0 if p == "approach" else 1 for p in phases], dtype=np.int16),
        direction=np.zeros(steps + 1, dtype=np.int16),
    )
    E.write_episode(root, meta, images, states)
    E.write_manifest(root)
    return root


@pytest.fixture
def fixture_root(tmp_path: Path) -> Path:
    return _synthetic(tmp_path / "fx")


def test_round_trip(fixture_root: Path) -> None:
    ep = E.load_episode(fixture_root, "door_00")
    assert len(ep.frames) == 4
    assert ep.frames[2].step == 40
    assert E.pixel_sha256(ep.frames[1].image_array()) == ep.frames[1].image_sha256
    assert ep.step_states.joints.shape == (61, 8)
    assert ep.boundaries() == [1]  # frames 0,1 approach (steps 0, 20), frames 2,3 grasp (steps 40, 60)


def test_writers_are_deterministic(tmp_path: Path) -> None:
    a = E.build_manifest(_synthetic(tmp_path / "a"))
    b = E.build_manifest(_synthetic(tmp_path / "b"))
    assert a == b


@pytest.mark.parametrize("rel", ["episode.json", "steps.npz", "frames/002.png"])
def test_any_flipped_byte_is_named(fixture_root: Path, rel: str) -> None:
    path = fixture_root / "episodes" / "door_00" / rel
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(E.EpisodeError, match=rel.replace("/", ".")):
        E.load_episode(fixture_root, "door_00")


def test_missing_and_extra_files_are_named(fixture_root: Path) -> None:
    ep_dir = fixture_root / "episodes" / "door_00"
    (ep_dir / "frames" / "001.png").unlink()
    with pytest.raises(E.EpisodeError, match=r"001\.png: missing"):
        E.load_episode(fixture_root, "door_00")
    E.write_manifest(fixture_root)
    (ep_dir / "notes.txt").write_text("hi")
    with pytest.raises(E.EpisodeError, match=r"notes\.txt: extra file"):
        E.load_episode(fixture_root, "door_00")


def test_extra_episode_folder_is_an_error(fixture_root: Path) -> None:
    shutil.copytree(fixture_root / "episodes" / "door_00", fixture_root / "episodes" / "door_01")
    with pytest.raises(E.EpisodeError, match="door_01: extra episode"):
        E.load_episodes(fixture_root)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m["frames"][1].update(joints=[float("nan")] * 8), "non-finite"),
        (lambda m: m["frames"][1].update(ee=[0.0] * 5), "ee must be a list of 6"),
        (lambda m: m["frames"][0].update(file="../../escape.png"), "leaves the episode folder"),
        (lambda m: m.pop("task"), "malformed episode metadata"),
        (lambda m: m.update(task="juggle"), "unknown task"),
    ],
)
def test_bad_metadata_is_a_clear_error(fixture_root: Path, mutate, message: str) -> None:
    path = fixture_root / "episodes" / "door_00" / "episode.json"
    meta = json.loads(path.read_text())
    mutate(meta)
    path.write_text(json.dumps(meta))
    E.write_manifest(fixture_root)  # the damage is "legitimate" as far as the manifest goes
    with pytest.raises(E.EpisodeError, match=message):
        E.load_episode(fixture_root, "door_00")


def test_truncated_png_is_a_clear_error(fixture_root: Path) -> None:
    path = fixture_root / "episodes" / "door_00" / "frames" / "003.png"
    path.write_bytes(path.read_bytes()[:40])
    E.write_manifest(fixture_root)
    ep = E.load_episode(fixture_root, "door_00")
    with pytest.raises(E.EpisodeError, match=r"003\.png: cannot decode image"):
        ep.frames[3].image_array()


@pytest.mark.parametrize("bad", ["../door_00", "door/00", "..", "", "Door 00", "a" * 80])
def test_episode_ids_cannot_leave_their_folder(fixture_root: Path, bad: str) -> None:
    with pytest.raises(E.EpisodeError, match="invalid episode id"):
        E.load_episode(fixture_root, bad)


def test_unknown_episode_lists_known_ones(fixture_root: Path) -> None:
    with pytest.raises(E.EpisodeError, match=r"no such episode.*door_00"):
        E.load_episode(fixture_root, "door_09")


def test_standard_ids() -> None:
    ids = E.standard_episode_ids()
    assert len(ids) == 22 and ids[0] == "door_00" and ids[-1] == "bin3_02"


def _fresh_process(monkeypatch) -> None:
    monkeypatch.setattr(E, "_PIXELS_VERIFIED", set())  # what a new process knows: nothing


def test_the_pixel_ledger_skips_decoding_only_bytes_verified_before(fixture_root: Path, tmp_path, monkeypatch):
    ledger = tmp_path / "cache" / E.PIXEL_LEDGER_FILE
    _fresh_process(monkeypatch)
    with E.pixel_ledger(ledger):
        for f in E.load_episode(fixture_root, "door_00").frames:
            f.image_bytes()
    assert len(ledger.read_text().splitlines()) == 4

    # a later process reads the ledger and decodes nothing (a decode would fail here)
    _fresh_process(monkeypatch)
    real_digest = E.pixel_sha256
    monkeypatch.setattr(E, "pixel_sha256", lambda rgb: pytest.fail("decoded a frame the ledger vouches for"))
    with E.pixel_ledger(ledger):
        for f in E.load_episode(fixture_root, "door_00").frames:
            f.image_bytes()
    monkeypatch.setattr(E, "pixel_sha256", real_digest)

    # damage behind a regenerated manifest: other bytes or another frame's digest are decoded and caught
    frames = fixture_root / "episodes" / "door_00" / "frames"
    a, b = (frames / "000.png").read_bytes(), (frames / "001.png").read_bytes()
    (frames / "000.png").write_bytes(b)
    (frames / "001.png").write_bytes(a)
    E.write_manifest(fixture_root)
    _fresh_process(monkeypatch)
    with E.pixel_ledger(ledger), pytest.raises(E.EpisodeError, match=r"000\.png: its pixels differ"):
        E.load_episode(fixture_root, "door_00").frames[0].image_bytes()
    from PIL import Image

    rgb = np.asarray(Image.open(frames / "001.png").convert("RGB")).copy()
    rgb[3, 3, 0] ^= 1
    Image.fromarray(rgb, "RGB").save(frames / "001.png", format="PNG")
    E.write_manifest(fixture_root)
    _fresh_process(monkeypatch)
    with E.pixel_ledger(ledger), pytest.raises(E.EpisodeError, match=r"001\.png: its pixels differ"):
        E.load_episode(fixture_root, "door_00").frames[1].image_bytes()


@pytest.mark.parametrize("damage", ["garbage", "directory in the way"])
def test_a_damaged_or_unwritable_pixel_ledger_only_means_decoding(fixture_root: Path, tmp_path, monkeypatch, damage):
    ledger = tmp_path / E.PIXEL_LEDGER_FILE
    if damage == "garbage":
        ledger.write_bytes(b"\xff\xfe not a ledger\n" + b"ab" * 64 + b"\n")
    else:
        ledger.mkdir()
    _fresh_process(monkeypatch)
    with E.pixel_ledger(ledger):
        assert E.load_episode(fixture_root, "door_00").frames[2].image_bytes().startswith(E.PNG_SIGNATURE)
    assert len(E._PIXELS_VERIFIED) == 1
    if damage == "garbage":
        assert len(ledger.read_text().splitlines()) == 1  # rewritten with the pair verified


def test_frame_images_are_the_frames_bytes_in_order_and_name_the_first_bad_frame(tmp_path: Path, monkeypatch):
    root = _synthetic(tmp_path / "fx", n_frames=9)
    frames = E.load_episode(root, "door_00").frames
    _fresh_process(monkeypatch)
    assert E.frame_images(frames) == [f.image_path.read_bytes() for f in frames]
    assert len(E._PIXELS_VERIFIED) == 9  # every frame decoded and checked, by whichever thread

    # two frames damaged behind a regenerated manifest: the earlier one is named, as a plain loop would
    from PIL import Image

    for i in (6, 3):
        path = frames[i].image_path
        rgb = np.asarray(Image.open(path).convert("RGB")).copy()
        rgb[1, 1, 1] ^= 1
        Image.fromarray(rgb, "RGB").save(path, format="PNG")
    E.write_manifest(root)
    _fresh_process(monkeypatch)
    with pytest.raises(E.EpisodeError, match=r"003\.png: its pixels differ"):
        E.frame_images(E.load_episode(root, "door_00").frames)
