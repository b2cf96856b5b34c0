"""Loading and writing episodes: the round trip, clear errors for bad metadata, frames read in order."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vlmproprio import episodes as E
from vlmproprio.episodes import pixels

from .support import fresh_process, synthetic


def test_round_trip(fixture_root: Path) -> None:
    ep = E.load_episode(fixture_root, "door_00")
    assert len(ep.frames) == 4
    assert ep.frames[2].step == 40
    assert E.pixel_sha256(ep.frames[1].image_array()) == ep.frames[1].image_sha256
    assert ep.step_states.joints.shape == (61, 8)
    assert ep.boundaries() == [1]  # frames 0,1 approach (steps 0, 20), frames 2,3 grasp (steps 40, 60)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m["frames"][1].update(joints=[float("nan")] * 8), "non-finite"),
        (lambda m: m["frames"][1].update(ee=[0.0] * 5), "ee must be a list of 6"),
        (lambda m: m["frames"][0].update(file="../../escape.png"), "leaves the episode folder"),
        (lambda m: m.pop("task"), "no 'task'"),
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


def test_unknown_episode_lists_known_ones(fixture_root: Path) -> None:
    with pytest.raises(E.EpisodeError, match=r"no such episode.*door_00"):
        E.load_episode(fixture_root, "door_09")


def test_frame_images_are_the_frames_bytes_in_order_and_name_the_first_bad_frame(tmp_path: Path, monkeypatch):
    root = synthetic(tmp_path / "fx", n_frames=9)
    frames = E.load_episode(root, "door_00").frames
    fresh_process(monkeypatch)
    assert E.frame_images(frames) == [f.image_path.read_bytes() for f in frames]
    assert len(pixels._PIXELS_VERIFIED) == 9  # every frame decoded and checked, by whichever thread

    # two frames damaged behind a regenerated manifest: the earlier one is named, as a plain loop would
    from PIL import Image

    for i in (6, 3):
        path = frames[i].image_path
        rgb = np.asarray(Image.open(path).convert("RGB")).copy()
        rgb[1, 1, 1] ^= 1
        Image.fromarray(rgb, "RGB").save(path, format="PNG")
    E.write_manifest(root)
    fresh_process(monkeypatch)
    with pytest.raises(E.EpisodeError, match=r"003\.png: its pixels differ"):
        E.frame_images(E.load_episode(root, "door_00").frames)
