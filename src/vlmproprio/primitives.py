"""Motion primitives: state changes thresholded into words ("moves forward and down", "closes the gripper").

One vocabulary serves three places: the recorder's ground-truth direction per
step, the `primitives` control condition (state as words instead of numbers),
and the reference captioner. Directions are in the robot's frame:
forward = +x (away from the base), left = +y, up = +z.
"""

from __future__ import annotations

from collections.abc import Sequence

AXIS_WORDS = (("forward", "backward"), ("left", "right"), ("up", "down"))
STILL = "still"
# A displacement counts when it is at least this long (m) ...
MIN_MOVE_M = 0.01
# ... and an axis is named when it carries at least this share of the displacement.
MIN_AXIS_SHARE = 0.35
# Finger opening change (m) that counts as opening or closing the gripper.
MIN_GRIP_M = 0.004


def direction_words(delta_xyz: Sequence[float], min_move: float = MIN_MOVE_M) -> list[str]:
    """Words for a displacement, largest axis first; [] when it is shorter than ``min_move``."""
    mags = [abs(float(d)) for d in delta_xyz[:3]]
    norm = sum(m * m for m in mags) ** 0.5
    if norm < min_move:
        return []
    order = sorted(range(3), key=lambda i: -mags[i])
    return [AXIS_WORDS[i][0 if delta_xyz[i] > 0 else 1] for i in order if mags[i] >= MIN_AXIS_SHARE * norm]


def direction_label(delta_xyz: Sequence[float], min_move: float = MIN_MOVE_M) -> str:
    """A canonical label for ground truth: "forward+down", "up", or "still" (axes in x, y, z order)."""
    words = direction_words(delta_xyz, min_move)
    if not words:
        return STILL
    canonical = [w for pair in AXIS_WORDS for w in pair if w in words]
    return "+".join(canonical)


def gripper_word(delta_opening: float, min_change: float = MIN_GRIP_M) -> str | None:
    if delta_opening <= -min_change:
        return "closes"
    if delta_opening >= min_change:
        return "opens"
    return None


def describe_step(delta_xyz: Sequence[float], delta_opening: float) -> str:
    """A short phrase for one interval: 'moves forward and down, closes the gripper'."""
    words = direction_words(delta_xyz)
    phrase = "moves " + " and ".join(words) if words else "holds still"
    grip = gripper_word(delta_opening)
    if grip:
        phrase += f", {grip} the gripper"
    return phrase
