"""The state-aware reference captioner (``reference-state``): NOT a vision-language model.

A positive control with a known effect. It shows whether the suite *can* detect the effect the paper
reports when a captioner really has it, so that "no effect" for a real model means something. It is a
fixed rule set, deterministic and instant; no answer of it may be read as what a VLM would write.

What it reads, per request (nothing else: never ground truth, never the episode files, never the
request tag):

* the ``# Process N`` line and the state lines after it (``prompts.state.parse_state_lines``), exactly
  what the condition put into the prompt, like the plain ``reference`` captioner it shares code with;
* the first image, only to tell which of the two shipped scenes it shows (``scene_of_image``: the top
  rows of the bin camera's picture are the warm wood floor, those of the Door camera the grey wall).
  That is what any viewer sees at a glance; it reads nothing else from the pixels.

What it knows beforehand, as a person who was told the task and shown the scene would (``SCENES``): the
object and the action of each scene, and the layout in the robot's frame. robosuite's defaults, documented
in ``vlmproprio.record.scenes`` and checked against the fixtures by tests/backends/test_reference_state.py:
the Panda's base position per arena, and for pick-and-place the target bin centred at x = 0.10 m,
y = 0.28 m (world frame) with its four compartments split at that centre (x below it: near the robot;
y above it: the robot's left, away from the source bin at y = -0.25 m). With joint angles only, the hand
position comes from the Panda's published forward kinematics (``panda_hand_position``).

What it writes:

* **with state** (``ee``, ``joint``, ``both`` and the numeric controls): per frame, the activity the hand's
  motion and gripper show (reaches, closes the gripper on the object, lifts it up, carries it left, lowers it
  into a compartment, releases it; Door: grasps the handle, turns it down, pulls the door toward the
  robot, lets go), so its frame captions change where the gripper or the motion changes; per group, those
  activities in order; as the final instruction, the task with the compartment where the hand puts the
  object down (the gripper opens over the target bin, or the hand's lowest point there) and the
  directions the hand moved while it held the object or the handle.
* **without state** (``none``, and ``primitives``, whose motion words it does not read): what any caption
  of the scene says -- the object and the action -- and nothing about where or which way.
* **with another episode's states** (``both_shuffled``): it reads them as faithfully as its own, so it names
  the partner episode's compartment and that episode's reversed directions: wrong by construction.
* **without images** (``state_only``): it cannot tell the scene, and answers as the plain ``reference``
  captioner does (motion words from the numbers).

So its effect is known in advance: trajectory correctness high with state, about zero without, and about
zero with shuffled state; segmentation boundaries follow gripper and motion changes.

Limits, by design: it knows only the two shipped scenes (Door and PickPlaceCereal with our bin camera; an
imported PickPlaceCan episode looks like the bin scene and would be captioned as a cereal box); a Process-1
frame sees only its own group's states, so a gripper change between two groups is described as the state
after it, not as the change; with noisy states (``both_noisy``) it reads the noise as motion, as it should.
"""

from __future__ import annotations

import io
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from vlmproprio.backends.reference import ReferenceBackend, prompt_states, reference_answer
from vlmproprio.chat import ChatRequest, ImagePart
from vlmproprio.prompts.state import ParsedState

RULES_VERSION = "state-rules-1"
MODEL_ID = "reference-state-rules"
NOTE = "rule-based state-aware captioner (a positive control), not a vision-language model"

DOOR, PICK_PLACE = "door", "pick_place"
# Scene from the first image: mean red minus mean blue of its top rows (the fixtures: bins 26-27, Door 5-7).
SCENE_ROWS = 32
DOOR_BELOW, BINS_ABOVE = 12.0, 20.0
# A hand displacement shorter than this (m) between two frames is no motion; a gripper change at least this
# large (m) is opening or closing; an opening below CLOSED_BELOW (m) holds something (open: ~0.08).
MIN_MOVE_M = 0.01
MIN_GRIP_CHANGE_M = 0.01
CLOSED_BELOW_M = 0.06


@dataclass(frozen=True)
class Scene:
    """What a person told the task and shown the scene knows: object, action, layout (world frame, m)."""

    name: str
    object: str
    task_sentence: str  # what any caption of the scene says, without state
    instruction_without_state: str
    base_xyz: tuple[float, float, float]  # the Panda's base in the world frame (robosuite's arena offset)
    bin_centre_xy: tuple[float, float] = (math.nan, math.nan)  # target bin (pick-and-place only)
    bin_gap_y: float = math.nan  # between the source bin (y below) and the target bin (y above)


SCENES = {
    DOOR: Scene(
        DOOR,
        "door handle",
        "opens the door by its handle",
        "Grasp the door handle and open the door.",
        base_xyz=(-0.56, 0.0, 0.912),  # robosuite: table arena, x = -0.16 - table length / 2
    ),
    PICK_PLACE: Scene(
        PICK_PLACE,
        "cereal box",
        "picks up the cereal box from the source bin and places it in the target bin",
        "Pick up the cereal box from the source bin and place it in the target bin.",
        base_xyz=(-0.5, -0.1, 0.912),  # robosuite: bins arena offset (-0.5, -0.1, 0)
        bin_centre_xy=(0.10, 0.28),  # robosuite PickPlace bin2_pos; the bins are 0.39 m x 0.49 m
        bin_gap_y=0.015,  # the source bin ends at y = -0.005, the target bin starts at 0.035
    ),
}


# ---------------------------------------------------------------------------------------------- what it sees


@lru_cache(maxsize=4096)
def _scene_of_png(data: bytes) -> str | None:
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.float64)
    top = rgb[:SCENE_ROWS]
    warmth = float(top[..., 0].mean() - top[..., 2].mean())
    if warmth < DOOR_BELOW:
        return DOOR
    if warmth > BINS_ABOVE:
        return PICK_PLACE
    return None


def scene_of_image(image: ImagePart) -> str | None:
    """Door or pick_place from one frame, or None when the picture is neither shipped scene (or unreadable)."""
    try:
        return _scene_of_png(image.data)
    except (OSError, ValueError):
        return None


# Panda forward kinematics: modified Denavit-Hartenberg parameters as Franka publishes them
# (a, d, alpha per joint, then the flange), and robosuite's grip site 0.0962 m beyond the flange.
_DH_A = (0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088, 0.0)
_DH_D = (0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0, 0.107)
_DH_ALPHA = (0.0, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, math.pi / 2, 0.0)
GRIP_SITE_M = 0.0962


def panda_hand_position(joints: Sequence[float], base_xyz: Sequence[float]) -> tuple[float, float, float]:
    """The grip site's world position from the 7 joint angles and the base position."""
    t = np.eye(4)
    for i in range(8):
        theta = float(joints[i]) if i < 7 else 0.0
        ca, sa, ct, st = math.cos(_DH_ALPHA[i]), math.sin(_DH_ALPHA[i]), math.cos(theta), math.sin(theta)
        t = t @ np.array(
            [
                [ct, -st, 0.0, _DH_A[i]],
                [st * ca, ct * ca, -sa, -sa * _DH_D[i]],
                [st * sa, ct * sa, ca, ca * _DH_D[i]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    p = t[:3, 3] + GRIP_SITE_M * t[:3, 2] + np.asarray(base_xyz, dtype=np.float64)
    return float(p[0]), float(p[1]), float(p[2])


@dataclass(frozen=True)
class Sample:
    """One frame as the rules use it: hand position (world, m) and gripper opening (None: not given)."""

    number: int
    pos: tuple[float, float, float]
    grip: float | None

    @property
    def holding(self) -> bool | None:
        return None if self.grip is None else self.grip < CLOSED_BELOW_M


def samples(states: Sequence[ParsedState], scene: Scene) -> list[Sample]:
    out = []
    for s in states:
        grip = s.joints[7] if s.joints is not None and len(s.joints) >= 8 else None
        if s.ee is not None and len(s.ee) >= 3:
            pos = (s.ee[0], s.ee[1], s.ee[2])
        elif s.joints is not None and len(s.joints) >= 7:
            pos = panda_hand_position(s.joints, scene.base_xyz)
        else:
            continue
        out.append(Sample(s.number, pos, grip))
    return out


# ---------------------------------------------------------------------------------------------- words


def compartment(pos: Sequence[float], scene: Scene) -> tuple[str, str]:
    """(row, side) of the target bin's compartment under a hand position."""
    cx, cy = scene.bin_centre_xy
    return ("near" if pos[0] < cx else "far"), ("left" if pos[1] > cy else "right")


def compartment_phrase(pos: Sequence[float], scene: Scene, long: bool = False) -> str:
    """'the near-left compartment of the target bin', with ``long`` also said in other words."""
    row, side = compartment(pos, scene)
    text = f"the {row}-{side} compartment of the target bin"
    if long:
        to_robot = "close to the robot" if row == "near" else "far from the robot"
        source = "next to the source bin" if side == "right" else "away from the source bin"
        text += f", the compartment {to_robot}, on its {side} side, {source}"
    return text


def over_target(pos: Sequence[float], scene: Scene) -> bool:
    return pos[1] > scene.bin_gap_y


def _short_compartment(pos: Sequence[float], scene: Scene) -> str:
    row, side = compartment(pos, scene)
    return f"the {row}-{side} compartment"


def _horizontal(dx: float, dy: float) -> str:
    """The main horizontal direction as words: 'to the left', 'forward, away from the robot', ..."""
    if abs(dy) >= abs(dx):
        return "to the left" if dy > 0 else "to the right"
    return "forward, away from the robot" if dx > 0 else "back toward the robot"


def _motion(cur: Sample, other: Sample, forward: bool) -> tuple[np.ndarray, float | None]:
    """Displacement and gripper change over the interval at a frame (to the next one, else from the previous)."""
    a, b = (cur, other) if forward else (other, cur)
    d = np.subtract(b.pos, a.pos)
    dg = None if a.grip is None or b.grip is None else b.grip - a.grip
    return d, dg


# Frame captions are short sentences with little in common between activities: the segmentation compares
# consecutive captions by sentence embedding, so a caption that changes with the activity (and stays the
# same within one) is what lets boundaries follow the gripper and the motion.


def activity(cur: Sample, nxt: Sample | None, prev: Sample | None, scene: Scene) -> str:
    """What the robot does at a frame, as one sentence."""
    if nxt is None and prev is None:  # a lone frame shows where the hand is, not how it moves
        return _still_activity(cur, scene)
    d, dg = _motion(cur, nxt, True) if nxt is not None else _motion(cur, prev, False)
    if scene.name == PICK_PLACE:
        return _pick_place_activity(cur, d, dg, scene)
    return _door_activity(cur, d, dg)


def _still_activity(cur: Sample, scene: Scene) -> str:
    if scene.name == PICK_PLACE:
        return {True: "The box is held still.", False: "The open hand pauses.", None: "The hand pauses."}[cur.holding]
    return "The handle is held still." if cur.holding else "The arm pauses in front of the door."


def _pick_place_activity(cur: Sample, d: np.ndarray, dg: float | None, scene: Scene) -> str:
    target = over_target(cur.pos, scene)
    if dg is not None and dg <= -MIN_GRIP_CHANGE_M:
        return "The gripper closes and grasps the cereal box."
    if dg is not None and dg >= MIN_GRIP_CHANGE_M:
        if target:
            return f"The fingers open and let go of the box in {_short_compartment(cur.pos, scene)}."
        return "The fingers open wide."
    if float(np.linalg.norm(d)) < MIN_MOVE_M:
        return _still_activity(cur, scene)
    holding = cur.holding
    hand = {False: "The open hand", None: "The hand"}
    dx, dy, dz = (float(v) for v in d)
    if abs(dz) >= math.hypot(dx, dy):
        if dz > 0:
            if holding:
                return "The box is lifted straight up."
            return f"{hand[holding]} rises up again." if target else f"{hand[holding]} rises up."
        where = _short_compartment(cur.pos, scene) if target else "the source bin"
        return f"It goes down into {where}." if holding else f"{hand[holding]} reaches down into {where}."
    bin_ = "the target bin" if dy > 0 else "the source bin"
    if holding:
        return f"The box is carried {_horizontal(dx, dy)}, over to {bin_}."
    return f"{hand[holding]} moves {_horizontal(dx, dy)}, toward {bin_}."


def _door_activity(cur: Sample, d: np.ndarray, dg: float | None) -> str:
    if dg is not None and dg <= -MIN_GRIP_CHANGE_M:
        return "Grasping the door handle: the fingers close on it."
    if dg is not None and dg >= MIN_GRIP_CHANGE_M:
        return "The fingers open and let go."
    if float(np.linalg.norm(d)) < MIN_MOVE_M:
        return _still_activity(cur, SCENES[DOOR])
    dx, dy, dz = (float(v) for v in d)
    if cur.holding:
        if abs(dz) >= math.hypot(dx, dy) or dz <= -MIN_MOVE_M:
            return f"The handle is turned {'down' if dz < 0 else 'up'}."
        if abs(dx) > abs(dy):  # the lever's end of travel moves the hand along x; the door swings it along y
            return "The handle is pressed forward." if dx > 0 else "The handle is drawn back toward the robot."
        side = "left" if dy > 0 else "right"
        if dx <= 0:
            return f"The door swings open toward the robot, to its {side}."
        return f"The door is pushed open away from the robot, to its {side}."
    hand = "The open hand" if cur.holding is False else "The hand"
    if abs(dz) >= math.hypot(dx, dy):
        return f"{hand} moves {'up' if dz > 0 else 'down'}."
    return f"{hand} moves {_horizontal(dx, dy)}."


# ---------------------------------------------------------------------------------------------- processes


def frame_captions(seq: Sequence[Sample], scene: Scene, k: int) -> list[str]:
    by_number = {s.number: s for s in seq}
    out = []
    for n in range(1, k + 1):
        cur = by_number.get(n)
        if cur is None:
            out.append(f"The robot {scene.task_sentence}.")
            continue
        out.append(activity(cur, by_number.get(n + 1), by_number.get(n - 1), scene))
    return out


def group_caption(seq: Sequence[Sample], scene: Scene) -> str:
    """The group's activities in order, repeats merged, after what the whole task is."""
    sentences: list[str] = []
    for i, cur in enumerate(seq):
        nxt = seq[i + 1] if i + 1 < len(seq) else None
        prev = seq[i - 1] if i > 0 else None
        a = activity(cur, nxt, prev, scene)
        if not sentences or sentences[-1] != a:
            sentences.append(a)
    return f"The robot {scene.task_sentence}. In these frames: " + " Then: ".join(sentences)


def _holding_run(seq: Sequence[Sample]) -> list[Sample]:
    """The longest run of frames with the gripper closed (the robot holds the object or the handle)."""
    best: list[Sample] = []
    run: list[Sample] = []
    for s in seq:
        if s.holding:
            run.append(s)
            if len(run) > len(best):
                best = list(run)
        else:
            run = []
    return best


def put_down_sample(seq: Sequence[Sample], scene: Scene) -> Sample | None:
    """Where the hand puts the object down: the gripper opening over the target bin after it held something,
    else (no gripper given, or the time runs backwards) the hand's lowest point over the target bin."""
    for a, b in itertools.pairwise(seq):
        opens = a.grip is not None and b.grip is not None and b.grip - a.grip >= MIN_GRIP_CHANGE_M
        if a.holding and opens and over_target(a.pos, scene):
            return a
    over = [s for s in seq if over_target(s.pos, scene)]
    return min(over, key=lambda s: s.pos[2]) if over else None


def pick_place_instruction(seq: Sequence[Sample], scene: Scene) -> str:
    put = put_down_sample(seq, scene)
    if put is None:
        return scene.instruction_without_state
    source = [s for s in seq if not over_target(s.pos, scene)]
    pick = min(source, key=lambda s: s.pos[2]) if source else None
    carry = ""
    if pick is not None:
        first, last = (pick, put) if pick.number < put.number else (put, pick)
        dx, dy = last.pos[0] - first.pos[0], last.pos[1] - first.pos[1]
        if math.hypot(dx, dy) >= MIN_MOVE_M:
            carry = f", carry it {_horizontal(dx, dy)}"
    return (
        f"Pick up the cereal box from the source bin, lift it up{carry} and place it in "
        f"{compartment_phrase(put.pos, scene, long=True)}."
    )


def door_instruction(seq: Sequence[Sample]) -> str:
    held = _holding_run(seq)
    if len(held) < 2:  # no gripper given: the stretch where the hand is lowest is where it holds the handle
        low = min(s.pos[2] for s in seq)
        lowest = [i for i, s in enumerate(seq) if s.pos[2] <= low + MIN_MOVE_M]
        held = list(seq[max(0, lowest[0] - 4) : lowest[-1] + 1])
    if len(held) < 2:
        return SCENES[DOOR].instruction_without_state
    vertical = [(a, b) for a, b in itertools.pairwise(held) if abs(b.pos[2] - a.pos[2]) >= MIN_MOVE_M]
    level = [(a, b) for a, b in itertools.pairwise(held) if abs(b.pos[2] - a.pos[2]) < MIN_MOVE_M]
    parts = ["Grasp the door handle"]
    if vertical:
        dz = sum(b.pos[2] - a.pos[2] for a, b in vertical)
        parts.append(f"turn it {'down' if dz < 0 else 'up'}")
    if level:
        dx = sum(b.pos[0] - a.pos[0] for a, b in level)
        dy = sum(b.pos[1] - a.pos[1] for a, b in level)
        side = "left" if dy > 0 else "right"
        if dx <= 0:
            parts.append(f"pull the door open toward the robot, swinging it to the robot's {side}")
        else:
            parts.append(f"push the door open away from the robot, swinging it to the robot's {side}")
    else:
        parts.append("open the door")
    return ", ".join(parts[:-1]) + " and " + parts[-1] + "."


def state_answer(request: ChatRequest) -> str:
    """The state-aware captioner's answer to one request (see the module docstring)."""
    # only the states after the '# Process N' line belong to this episode (the worked example has its own)
    process, states = prompt_states(request)
    scene_name = scene_of_image(request.images[0]) if request.images else None
    if scene_name is None:  # no picture of a known scene: it does not know the task
        return reference_answer(request)
    scene = SCENES[scene_name]
    seq = samples(states, scene)
    if process == 1:
        k = max([len(request.images), *(s.number for s in seq)])
        return "\n".join(f"Frame {n}: {c}" for n, c in enumerate(frame_captions(seq, scene, k), start=1))
    if process == 2:
        return group_caption(seq, scene) if seq else f"The robot {scene.task_sentence}."
    if len(seq) < 2:
        return scene.instruction_without_state
    return pick_place_instruction(seq, scene) if scene.name == PICK_PLACE else door_instruction(seq)


class ReferenceStateBackend(ReferenceBackend):
    """Task-aware captions from the state numbers: a positive control with a known effect, not a VLM."""

    model_id = MODEL_ID
    rules_version = RULES_VERSION
    note = NOTE

    def answer(self, request: ChatRequest) -> str:
        return state_answer(request)
