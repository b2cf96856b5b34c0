"""Conditions: what the model is given besides the task prompt, per sampled frame.

The paper's four conditions differ only in the state put next to each image:

* ``none``   images only; no state section, and the guideline that refers to state is dropped
* ``ee``     images + end-effector pose (x, y, z, roll, pitch, yaw)
* ``joint``  images + joint state (7 angles + gripper opening)
* ``both``   images + both

Four controls make the comparison falsifiable:

* ``both_shuffled`` both states, but from another episode of the same task (for bins one with a different
  target compartment), played backwards in time and resampled to this episode's frame count: numbers that
  look real but carry the wrong trajectory. A model that merely writes longer captions when it sees numbers
  scores as well here as under ``both``; one that reads them does worse. With no other episode of the task
  available the episode's own states are played backwards.
* ``both_noisy``    both states plus Gaussian noise, seeded by the episode id, with standard deviations
  ``NOISE_STD``: joint angles 0.05 rad, gripper 0.005 m, position 0.02 m, roll/pitch/yaw 0.05 rad (small
  against the motions, large against the printed precision of 0.001).
* ``state_only``    both states and no images at all.
* ``primitives``    images + the state turned into motion-primitive words (vlmproprio.primitives) instead
  of numbers: for frame n the motion of the hand from frame n to n+1 (the last frame repeats the motion
  into it).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from vlmproprio.episodes import Episode
from vlmproprio.errors import UsageError
from vlmproprio.primitives import describe_step


@dataclass(frozen=True)
class Condition:
    name: str
    description: str
    joints: bool = False
    ee: bool = False
    images: bool = True
    words: bool = False  # state as motion-primitive words instead of numbers
    source: str = "own"  # own | shuffled | noisy
    control: bool = False

    @property
    def numeric_state(self) -> bool:
        return self.joints or self.ee

    @property
    def has_state(self) -> bool:
        return self.numeric_state or self.words


PAPER_CONDITIONS = ("none", "ee", "joint", "both")
CONTROLS = ("both_shuffled", "both_noisy", "state_only", "primitives")
BASELINE = "none"

CONDITIONS: dict[str, Condition] = {
    c.name: c
    for c in (
        Condition("none", "images only"),
        Condition("ee", "images + end-effector pose", ee=True),
        Condition("joint", "images + joint angles and gripper", joints=True),
        Condition("both", "images + joints + end-effector pose", joints=True, ee=True),
        Condition(
            "both_shuffled",
            "images + another episode's states, reversed",
            joints=True,
            ee=True,
            source="shuffled",
            control=True,
        ),
        Condition("both_noisy", "images + noisy states", joints=True, ee=True, source="noisy", control=True),
        Condition("state_only", "states only, no images", joints=True, ee=True, images=False, control=True),
        Condition("primitives", "images + state as motion words", words=True, control=True),
    )
}

# joint angles (7) rad, gripper m, x y z m, roll pitch yaw rad
NOISE_STD = np.array([0.05] * 7 + [0.005]), np.array([0.02] * 3 + [0.05] * 3)


def get_condition(name: str) -> Condition:
    try:
        return CONDITIONS[name]
    except KeyError:
        raise UsageError(
            f"unknown condition {name!r}; choose from {', '.join(CONDITIONS)} (or 'paper', 'controls', 'all')"
        ) from None


def parse_conditions(spec: str | Iterable[str]) -> list[Condition]:
    """'all' | 'paper' | 'controls' | comma-separated names (or a list of those) -> conditions, no repeats."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names: list[str] = []
    for raw in items:
        for item in raw.split(","):
            item = item.strip()
            group = {"all": [*PAPER_CONDITIONS, *CONTROLS], "paper": PAPER_CONDITIONS, "controls": CONTROLS}
            for n in group.get(item, [item]):
                if n and n not in names:
                    names.append(n)
    if not names:
        raise UsageError("no condition given")
    return [get_condition(n) for n in names]


@dataclass(frozen=True)
class FrameStates:
    """The state a condition shows for each sampled frame (None where it shows none)."""

    joints: np.ndarray | None  # (N, 8)
    ee: np.ndarray | None  # (N, 6)
    words: list[str] | None


def _resample(a: np.ndarray, n: int) -> np.ndarray:
    idx = np.rint(np.linspace(0, len(a) - 1, n)).astype(int)
    return a[idx]


def _partner(episode: Episode, peers: Sequence[Episode]) -> Episode | None:
    """The next episode (by id, cyclically) of the same task, preferring a different target compartment."""
    same_task = sorted((p for p in peers if p.task == episode.task), key=lambda p: p.episode_id)
    others = [p for p in same_task if p.episode_id != episode.episode_id]
    if episode.target_bin is not None:
        other_bin = [p for p in others if p.target_bin is None or p.target_bin.index != episode.target_bin.index]
        others = other_bin or others
    if not others:
        return None
    later = [p for p in others if p.episode_id > episode.episode_id]
    return (later or others)[0]


def _noise_rng(episode: Episode) -> np.random.Generator:
    seed = int.from_bytes(hashlib.sha256(f"both_noisy/{episode.episode_id}".encode()).digest()[:8], "little")
    return np.random.default_rng(seed)


def motion_words(ee: np.ndarray, joints: np.ndarray) -> list[str]:
    n = len(ee)
    out = []
    for i in range(n):
        a, b = (i, i + 1) if i + 1 < n else (max(i - 1, 0), i)
        out.append("the hand " + describe_step(ee[b, :3] - ee[a, :3], joints[b, 7] - joints[a, 7]))
    return out


def frame_states(episode: Episode, condition: Condition, peers: Sequence[Episode] = ()) -> FrameStates:
    joints, ee = episode.joints_array(), episode.ee_array()
    if condition.source == "shuffled":
        partner = _partner(episode, peers)
        src_j, src_e = (partner.joints_array(), partner.ee_array()) if partner else (joints, ee)
        n = len(episode.frames)
        joints, ee = _resample(src_j[::-1], n), _resample(src_e[::-1], n)
    elif condition.source == "noisy":
        rng = _noise_rng(episode)
        joints = joints + rng.normal(0.0, 1.0, joints.shape) * NOISE_STD[0]
        ee = ee + rng.normal(0.0, 1.0, ee.shape) * NOISE_STD[1]
    return FrameStates(
        joints=joints if condition.joints else None,
        ee=ee if condition.ee else None,
        words=motion_words(ee, joints) if condition.words else None,
    )
