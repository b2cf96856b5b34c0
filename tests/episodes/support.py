"""A small synthetic fixture set written by the episode writers themselves, and a process's fresh pixel memory."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vlmproprio import episodes as E
from vlmproprio.episodes import pixels


def synthetic(root: Path, episode_id: str = "door_00", n_frames: int = 4) -> Path:
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


def fresh_process(monkeypatch) -> None:
    monkeypatch.setattr(pixels, "_PIXELS_VERIFIED", set())  # what a new process knows: nothing
