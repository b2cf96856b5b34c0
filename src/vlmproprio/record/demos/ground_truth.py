"""Ground-truth phases of a replayed demo, from simulator signals per step.

-----------------------------------
Without a scripted operator, phases come from signals per step. An *onset* is
the first step of a change: a signal rises by a threshold above its running
minimum (or falls by it below its running maximum), and the change began at
the earliest step of the run of steps before that in which it moved at least
1/40 of the threshold per step (a change made within two seconds; two slower
steps may interrupt the run). A rate rather than a distance from the extreme,
so that slow drift (a held lever sagging, fingers easing open on a handle)
does not pass for the start of a motion. The gripper is *closing* / *opening*
when the finger opening (``joints[7]``) falls / rises by 5 mm.

* door (``scenes.DOOR_PHASES``): approach; *grasp handle* from the closing
  onset after the last fully open step before the lever turns (with no turn
  and no pull: the first closing onset); *turn handle down* from the lever's
  onset (latch joint +0.1 rad); *pull door open* from the hinge's onset
  (+0.05 rad); *release and retreat* from the first of the fingers opening or
  the lever turning back (-0.1 rad) after the pull.
* pick_place (``scenes.bin_phases(k)``, PickPlaceCereal and PickPlaceCan):
  approach; *descend* from the step after the grip site was last within 1 cm
  of its highest point, over the stretch before the grasp in which it stayed
  above the object (within 5 cm horizontally); *grasp* from the closing onset
  after the last fully open step before the lift (no lift: the first closing
  onset); *lift* from the object's onset 2 cm up; *transport to bin k* from
  its onset 3 cm away horizontally from where it was lifted; *lower* from its
  onset 2 cm down since; *release* from the fingers' opening onset (the
  fingers move once the gripper's target has passed the object, a few steps
  after the command); *retreat* from the grip site's onset 3 cm away from
  where the release began. The target compartment k is the one the object
  ends in; an object in none gets robosuite's own compartment for it (cereal
  2, can 3) and ``success: false``.
* lift (``scenes.LIFT_PHASES``): as pick_place without transport and lower.

A phase whose onset is not found, or not after the previous one, is left out
(its steps stay in the previous phase). Directions are the recorder's:
displacement of the end effector over one frame interval.

"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vlmproprio.record import scenes

# Phase onsets (see the module docstring): how far a signal must move, ...
GRIP_CHANGE_M, GRIP_OPEN_TOL_M = 0.005, 0.005
LATCH_TURN_RAD = 0.1
HINGE_OPEN_RAD = 0.05
LIFT_M = 0.02
TRANSPORT_M = 0.03
LOWER_M = 0.02
NEAR_XY_M, DESCENT_START_M = 0.05, 0.01
RETREAT_M = 0.03
# ... and a motion is under way while it moves at least 1/RISE_STEPS of that per step (two seconds for the
# whole change), with up to ONSET_GAP slower steps in between.
RISE_STEPS, ONSET_GAP = 40, 2


def onset(x: np.ndarray, start: int | None, rise: float) -> int | None:
    """First step of a rise of ``x`` by ``rise`` above its running minimum since ``start`` (None: not found).

    From the step where the rise is complete, walk back through the steps where ``x`` grows faster than
    ``rise / RISE_STEPS`` per step (two-step average, gaps of up to ONSET_GAP slow steps allowed): the rise
    began at the earliest of them. A rate, not a distance from the minimum, so that slow drift (a held lever
    sagging, fingers easing open on a handle) is not taken for the start of the motion."""
    if start is None or start >= len(x):
        return None
    x = np.asarray(x, dtype=np.float64)
    seg = x[start:]
    hits = np.nonzero(seg - np.minimum.accumulate(seg) >= rise)[0]
    if len(hits) == 0:
        return None
    k = start + int(hits[0])
    rate = np.zeros(len(x))  # rate[j]: growth per step into step j
    rate[1:] = np.diff(x)
    rate[2:] = (x[2:] - x[:-2]) / 2
    fast = rate > rise / RISE_STEPS
    first, gap = k, 0
    for j in range(k, start - 1, -1):
        if fast[j]:
            first, gap = j, 0
        else:
            gap += 1
            if gap > ONSET_GAP:
                break
    return first


def closing_onset(opening: np.ndarray, before: int | None) -> int | None:
    """The gripper's closing onset after its last fully open step before ``before`` (the closing that led to
    what happened there), or with ``before`` None (nothing happened) its first closing onset."""
    if before is None:
        return onset(-opening, 0, GRIP_CHANGE_M)
    if before <= 0:
        return None
    top = float(np.max(opening[:before]))
    s0 = int(np.nonzero(opening[:before] >= top - GRIP_OPEN_TOL_M)[0][-1])
    c = onset(-opening, s0, GRIP_CHANGE_M)
    return c if c is not None and c < before else None


def descent_start(grip: np.ndarray, obj: np.ndarray, grasp: int | None) -> int | None:
    """Where the hand's final descent onto the object begins: the last step near its highest point over the
    stretch before ``grasp`` during which it stayed above the object."""
    if grasp is None:
        return None
    near = np.linalg.norm(grip[: grasp + 1, :2] - obj[grasp, :2], axis=1) <= NEAR_XY_M
    if not near[grasp]:
        return None
    s = grasp
    while s > 0 and near[s - 1]:
        s -= 1
    z = grip[s : grasp + 1, 2]
    high = np.nonzero(z >= z.max() - DESCENT_START_M)[0]
    d0 = s + int(high[-1]) + 1
    return d0 if d0 < grasp else None


def label_steps(n: int, onsets: Sequence[tuple[str, int | None]]) -> list[str]:
    """Per-step phase names: the first phase from step 0, each later one from its onset when found and after the
    previous phase's start."""
    labels: list[str] = []
    starts: list[tuple[int, str]] = [(0, onsets[0][0])]
    for name, start in onsets[1:]:
        if start is not None and starts[-1][0] < start < n:
            starts.append((start, name))
    for i, (start, name) in enumerate(starts):
        end = starts[i + 1][0] if i + 1 < len(starts) else n
        labels.extend([name] * (end - start))
    return labels


def door_phases(opening: np.ndarray, latch: np.ndarray, hinge: np.ndarray) -> list[str]:
    pull = onset(hinge, 0, HINGE_OPEN_RAD)
    turn = onset(latch, 0, LATCH_TURN_RAD)
    anchor = turn if turn is not None else pull
    grasp = closing_onset(opening, anchor)
    after = next((e for e in (pull, turn, grasp) if e is not None), None)
    release = None
    if after is not None:
        ends = [onset(opening, after, GRIP_CHANGE_M), onset(-latch, after, LATCH_TURN_RAD)]
        ends = [e for e in ends if e is not None]
        release = min(ends) if ends else None
    names = scenes.DOOR_PHASES
    return label_steps(
        len(opening), [(names[0], 0), (names[1], grasp), (names[2], turn), (names[3], pull), (names[4], release)]
    )


def pick_phases(
    opening: np.ndarray, grip: np.ndarray, obj: np.ndarray, names: Sequence[str], transport: bool
) -> list[str]:
    """Phases of a pick (and place): names are approach, descend, grasp, lift, [transport, lower,] release,
    retreat."""
    z = obj[:, 2]
    lift = onset(z, 0, LIFT_M)
    grasp = closing_onset(opening, lift)
    descend = descent_start(grip, obj, grasp)
    trans = lower = None
    if transport and lift is not None:
        moved = np.linalg.norm(obj[:, :2] - obj[lift, :2], axis=1)
        trans = onset(moved, lift, TRANSPORT_M)
        lower = onset(-z, trans, LOWER_M)
    after = next((e for e in (lower, trans, lift, grasp) if e is not None), None)
    release = onset(opening, after, GRIP_CHANGE_M)
    retreat = None
    if release is not None:
        away = np.linalg.norm(grip - grip[release], axis=1)
        retreat = onset(away, release, RETREAT_M)
    events = [descend, grasp, lift] + ([trans, lower] if transport else []) + [release, retreat]
    return label_steps(len(opening), [(names[0], 0), *zip(names[1:], events, strict=True)])
