"""The episode vocabulary: file names, dimensions, ids, the error, and the plain value types.

State conventions (also written into every episode.json):

* ``joints``: the 7 Panda joint angles in rad, then the gripper opening in m
  (distance between the two finger joints, ~0 closed, ~0.08 fully open).
* ``ee``: x, y, z of the grip site in m in the world frame, then roll, pitch,
  yaw in rad: extrinsic x-y-z Euler angles of ``robot0_eef_quat``, unwrapped
  along the episode (``numpy.unwrap``), so they may leave (-pi, pi] but never jump.
* directions are in the robot's frame: forward = +x (away from the base),
  left = +y, up = +z.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from vlmproprio.errors import VlmproprioError

FORMAT_VERSION = 1
# every task an episode may name; each has a scoring lexicon (vlmproprio/lexicons/<task>.json)
TASKS = ("door", "pick_place", "lift", "stack")
JOINT_DIM = 8
EE_DIM = 6
MANIFEST_NAME = "manifest.json"
EPISODE_FILE = "episode.json"
STEPS_FILE = "steps.npz"
FRAMES_DIR = "frames"

# Episode ids become path components: keep them to a closed alphabet so that no id can leave its folder.
EPISODE_ID_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")

STATE_CONVENTIONS = {
    "joints": "7 joint angles (rad) then gripper opening (m, distance between the finger joints)",
    "ee": "x, y, z of the grip site (m, world frame) then roll, pitch, yaw (rad, extrinsic xyz Euler "
    "of robot0_eef_quat, unwrapped along the episode)",
    "directions": "robot frame: forward=+x (away from the base), left=+y, up=+z",
}


class EpisodeError(VlmproprioError):
    """An episode or fixture set that cannot be used; the message names the file and what is wrong."""


@dataclass(frozen=True)
class TargetBin:
    """Where the object must go in PickPlace, in robosuite's index and in words as seen in the image."""

    index: int
    row: str  # "near" | "far"  (from the robot; near is the bottom row of the image)
    side: str  # "left" | "right" (the robot's and the image's left/right)
    description: str


@dataclass(frozen=True)
class StepStates:
    """Full-rate state and ground truth at every sim step (arrays of length ``steps + 1``)."""

    step: np.ndarray  # (T,) int
    joints: np.ndarray  # (T, 8)
    ee: np.ndarray  # (T, 6)
    phase: np.ndarray  # (T,) int index into Episode.phase_names
    direction: np.ndarray  # (T,) int index into Episode.direction_vocab


@dataclass(frozen=True)
class PhaseSpan:
    name: str
    start_step: int
    end_step: int  # inclusive


def check_episode_id(episode_id: str) -> str:
    if not isinstance(episode_id, str) or not EPISODE_ID_RE.match(episode_id):
        raise EpisodeError(
            f"invalid episode id {episode_id!r}: use lower-case letters, digits, '_' and '-' "
            "(no path separators, no '..')"
        )
    return episode_id


def standard_episode_ids() -> list[str]:
    """The paper's 22: 10 Door episodes and 3 per target bin for PickPlaceCereal."""
    return [f"door_{s:02d}" for s in range(10)] + [f"bin{b}_{s:02d}" for b in range(4) for s in range(3)]
