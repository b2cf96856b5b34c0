"""Conditions: what the model is given besides the task prompt, per sampled frame.

The paper's four conditions differ only in the state put next to each image:

* ``none``   images only; no state section, and the guideline that refers to state is dropped
* ``ee``     images + end-effector pose (x, y, z, roll, pitch, yaw)
* ``joint``  images + joint state (7 angles + gripper opening)
* ``both``   images + both

Five controls make the comparison falsifiable:

* ``both_shuffled`` both states, but from the partner episode (below), played backwards in time and
  resampled to this episode's frame count: numbers that look real but carry the wrong trajectory. A model
  that merely writes longer captions when it sees numbers scores as well here as under ``both``; one that
  reads them does worse. Pick-and-place is nearly symmetric in time, so reversed states still correlate with
  the true ones (the score's meta.json records how much, per dimension): a weak control.
* ``both_permuted`` the partner's states, resampled, then put in a random order (seeded by the episode id):
  the same numbers with no timeline at all, so they carry no information about when anything happens in
  this episode -- the control that can falsify a segmentation claim.
* the partner of an episode is the episode ``len // 2`` places further in the task's episodes sorted by id
  (cyclically), so every episode of a task serves as partner exactly once; for the bin episodes (3 per
  compartment) that is always one with another target compartment. With no other episode of the task the
  episode's own states are used.
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
from vlmproprio.errors import UsageError, did_you_mean
from vlmproprio.primitives import describe_step


@dataclass(frozen=True)
class Condition:
    name: str
    description: str
    joints: bool = False
    ee: bool = False
    images: bool = True
    words: bool = False  # state as motion-primitive words instead of numbers
    source: str = "own"  # own | shuffled | permuted | noisy
    control: bool = False

    @property
    def numeric_state(self) -> bool:
        return self.joints or self.ee

    @property
    def has_state(self) -> bool:
        return self.numeric_state or self.words


PAPER_CONDITIONS = ("none", "ee", "joint", "both")
CONTROLS = ("both_shuffled", "both_permuted", "both_noisy", "state_only", "primitives")
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
        Condition(
            "both_permuted",
            "images + another episode's states in random order",
            joints=True,
            ee=True,
            source="permuted",
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
            f"unknown condition {name!r}{did_you_mean(name, [*CONDITIONS, 'paper', 'controls', 'all'])}; "
            f"choose from {', '.join(CONDITIONS)} (or 'paper', 'controls', 'all')"
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
    """The episode ``len // 2`` places further among the task's episodes sorted by id (cyclically): a
    permutation of the task's episodes, so each one is a partner exactly once; None if the task has no other."""
    same_task = sorted({p.episode_id: p for p in [*peers, episode] if p.task == episode.task}.values(),
                       key=lambda p: p.episode_id)  # fmt: skip
    n = len(same_task)
    if n < 2:
        return None
    i = next(i for i, p in enumerate(same_task) if p.episode_id == episode.episode_id)
    return same_task[(i + n // 2) % n]


def _permutation(episode: Episode, n: int) -> np.ndarray:
    seed = int.from_bytes(hashlib.sha256(f"both_permuted/{episode.episode_id}".encode()).digest()[:8], "little")
    return np.random.default_rng(seed).permutation(n)


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
    if condition.source in ("shuffled", "permuted"):
        partner = _partner(episode, peers)
        src_j, src_e = (partner.joints_array(), partner.ee_array()) if partner else (joints, ee)
        n = len(episode.frames)
        if condition.source == "shuffled":
            joints, ee = _resample(src_j[::-1], n), _resample(src_e[::-1], n)
        else:
            order = _permutation(episode, n)
            joints, ee = _resample(src_j, n)[order], _resample(src_e, n)[order]
    elif condition.source == "noisy":
        rng = _noise_rng(episode)
        joints = joints + rng.normal(0.0, 1.0, joints.shape) * NOISE_STD[0]
        ee = ee + rng.normal(0.0, 1.0, ee.shape) * NOISE_STD[1]
    return FrameStates(
        joints=joints if condition.joints else None,
        ee=ee if condition.ee else None,
        words=motion_words(ee, joints) if condition.words else None,
    )


STATE_DIMENSIONS = (*(f"joint{i}" for i in range(1, 8)), "gripper", "x", "y", "z", "roll", "pitch", "yaw")


def state_correlations(
    episode: Episode, condition: Condition, peers: Sequence[Episode] = ()
) -> dict[str, float | None]:
    """Pearson r, per state dimension, between the numbers a condition shows and the episode's true states
    over its frames (None where either side is constant, or the condition shows no numbers): how much a
    control still tells about the episode."""
    if not condition.numeric_state:
        return {}
    shown = frame_states(episode, condition, peers)
    full = frame_states(episode, Condition("both", "", joints=True, ee=True), peers)
    a = np.concatenate([full.joints, full.ee], axis=1)
    b = np.concatenate([shown.joints if shown.joints is not None else np.full_like(full.joints, np.nan),
                        shown.ee if shown.ee is not None else np.full_like(full.ee, np.nan)], axis=1)  # fmt: skip
    out: dict[str, float | None] = {}
    for i, name in enumerate(STATE_DIMENSIONS):
        x, y = a[:, i], b[:, i]
        if not np.isfinite(y).all() or np.ptp(x) == 0 or np.ptp(y) == 0:
            out[name] = None
            continue
        xc, yc = x - x.mean(), y - y.mean()
        out[name] = float(np.dot(xc, yc) / np.sqrt(np.dot(xc, xc) * np.dot(yc, yc)))
    return out
