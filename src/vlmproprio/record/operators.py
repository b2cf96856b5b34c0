"""Scripted operators that drive the Panda like a person with a 3-D mouse.

The paper's episodes were teleoperated; ours are scripted, but paced like a
person: each seed draws a ``Style`` (cruise speed, pauses between sub-goals,
hand tremor, slightly different approach paths), so episodes average the
paper's lengths (Door ~580 steps, bins ~539) and differ from each other.

An operator is a generator of ``(phase, action)`` pairs, one per sim step,
reading the simulator's fresh state at every step. Actions are for robosuite's
default OSC_POSE controller: 3 position deltas (scaled by 0.05 m), 3
axis-angle deltas (scaled by 0.5 rad), gripper (-1 open, +1 close).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vlmproprio.record import scenes

POS_SCALE, ROT_SCALE = 0.05, 0.5  # OSC_POSE output_max in robosuite's default_panda.json
OPEN, CLOSE = -1.0, 1.0
TRANSIT = 1.6  # pace of moves through free space, relative to the style's working speed
Step = tuple[str, np.ndarray]


@dataclass(frozen=True)
class Style:
    """How one simulated person operates: drawn once per episode from its seed."""

    speed: float  # cruise speed, m per step
    rot_speed: float  # rad per step
    gain: float  # fraction of the remaining distance covered per step near a target (smooth slow-down)
    tremor: float  # std of hand tremor, m per step
    pause: tuple[int, int]  # range of steps a person pauses between sub-goals
    lateral: float  # sideways offset of approach waypoints, m
    height: float  # extra height of approach waypoints, m
    turn_steps: int  # Door: steps to turn the lever down
    pull_speed: float  # Door: hinge rad per step while pulling

    @classmethod
    def sample(cls, rng: np.random.Generator) -> Style:
        return cls(
            speed=float(rng.uniform(0.0115, 0.0163)),
            rot_speed=float(rng.uniform(0.081, 0.115)),
            gain=float(rng.uniform(0.10, 0.16)),
            tremor=float(rng.uniform(0.0004, 0.0010)),
            pause=(int(rng.integers(5, 10)), int(rng.integers(14, 26))),
            lateral=float(rng.uniform(-0.04, 0.04)),
            height=float(rng.uniform(0.0, 0.06)),
            turn_steps=int(rng.integers(60, 85)),
            pull_speed=float(rng.uniform(0.0026, 0.0036)),
        )


class Hand:
    """Servoes the grip site towards poses at the style's pace, with low-pass hand tremor."""

    def __init__(self, env, style: Style, rng: np.random.Generator):
        self.env, self.style, self.rng = env, style, rng
        self.site = env.robots[0].eef_site_id["right"]
        self._tremor = np.zeros(3)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.env.sim.data
        return d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy()

    def error(self, tpos: np.ndarray, tR: np.ndarray) -> tuple[float, float]:
        pos, R = self.pose()
        return float(np.linalg.norm(tpos - pos)), float(np.linalg.norm(Rotation.from_matrix(tR @ R.T).as_rotvec()))

    def action(
        self, tpos: np.ndarray, tR: np.ndarray, grip: float, speed: float | None = None, pace: float = 1.0
    ) -> np.ndarray:
        """One step toward a pose. ``speed`` overrides the style's cruise speed; ``pace`` scales it (and the
        turning rate): people cross free space faster than they work near objects."""
        pos, R = self.pose()
        v = (tpos - pos) * (1.0 if speed is not None else self.style.gain * 4.0)
        limit = speed if speed is not None else self.style.speed * pace
        n = np.linalg.norm(v)
        if n > limit:
            v *= limit / n
        # tremor: an AR(1) process, so the hand wobbles smoothly instead of jittering every step
        self._tremor = 0.85 * self._tremor + self.rng.normal(0.0, self.style.tremor, 3)
        v = v + self._tremor
        rv = Rotation.from_matrix(tR @ R.T).as_rotvec()
        rn = np.linalg.norm(rv)
        if rn > self.style.rot_speed * pace:
            rv *= self.style.rot_speed * pace / rn
        a = np.zeros(7)
        a[:3] = np.clip(v / POS_SCALE, -1, 1)
        a[3:6] = np.clip(rv / ROT_SCALE, -1, 1)
        a[6] = grip
        return a

    def move(
        self,
        phase: str,
        tpos,
        tR,
        grip: float,
        tol: float = 0.01,
        rtol: float = 0.05,
        max_steps: int = 300,
        pace: float = 1.0,
    ) -> Iterator[Step]:
        tpos = np.asarray(tpos, float)
        for _ in range(max_steps):
            e, r = self.error(tpos, tR)
            if e < tol and r < rtol:
                return
            yield phase, self.action(tpos, tR, grip, pace=pace)

    def hold(self, phase: str, grip: float, steps: int, pos=None, R=None) -> Iterator[Step]:
        p, Rc = self.pose()
        p = p if pos is None else np.asarray(pos, float)
        R = Rc if R is None else R
        for _ in range(steps):
            yield phase, self.action(p, R, grip)

    def pause(self, phase: str, grip: float) -> Iterator[Step]:
        """A person's pause between sub-goals: hold the pose for a while."""
        lo, hi = self.style.pause
        yield from self.hold(phase, grip, int(self.rng.integers(lo, hi + 1)))


def frame_zx(z, x, R_cur) -> np.ndarray:
    """Site rotation with approach axis z and finger-closing axis ±x, whichever needs less rotation from R_cur."""
    z = np.asarray(z, float) / np.linalg.norm(z)
    x = np.asarray(x, float) - np.dot(x, z) * z
    x /= np.linalg.norm(x)
    best = None
    for sx in (1.0, -1.0):
        R = np.stack([sx * x, np.cross(z, sx * x), z], axis=1)
        ang = np.linalg.norm(Rotation.from_matrix(R @ R_cur.T).as_rotvec())
        if best is None or ang < best[0]:
            best = (ang, R)
    return best[1]


# ---------------------------------------------------------------------------------------------- Door


def door_operator(env, hand: Hand) -> Iterator[Step]:
    import mujoco

    m, d = env.sim.model._model, env.sim.data._data
    latch = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "Door_latch_joint")
    hinge = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "Door_hinge")
    panel = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "Door_panel")
    handle = env.sim.data.site_xpos[env.sim.model.site_name2id("Door_handle")].copy()
    latch_anchor, latch_axis = d.xanchor[latch].copy(), d.xaxis[latch].copy()
    hinge_anchor, hinge_axis = d.xanchor[hinge].copy(), d.xaxis[hinge].copy()
    normal = d.geom_xmat[panel].reshape(3, 3)[:, 1].copy()
    out = normal if np.dot(handle - d.geom_xpos[panel], normal) > 0 else -normal  # from the door toward the robot
    out[2] = 0.0
    out /= np.linalg.norm(out)
    side = np.cross([0.0, 0.0, 1.0], out)
    st = hand.style
    _, R0 = hand.pose()
    # Fingers close vertically around the lever. The least-rotation grasp leaves joint 7 near 2.0 rad and the
    # lever turn (which raises q7) would hit its limit, so grasp with the fingers swapped (rotated by pi about
    # the approach axis), reached through a -pi/2 waypoint so the direction of rotation is never ambiguous.
    Rb = frame_zx(-out, np.array([0.0, 0.0, 1.0]), R0)
    Rm = Rb @ Rotation.from_rotvec([0, 0, -np.pi / 2]).as_matrix()
    Rg = Rb @ Rotation.from_rotvec([0, 0, -np.pi]).as_matrix()
    grasp = handle + 0.01 * out
    standoff = grasp + 0.12 * out + st.lateral * side + np.array([0, 0, st.height])

    phase = scenes.DOOR_PHASES
    yield from hand.hold(phase[0], OPEN, 5)
    yield from hand.move(phase[0], standoff, Rb, OPEN, tol=0.03, rtol=0.3, pace=TRANSIT)
    yield from hand.move(phase[0], standoff, Rm, OPEN, tol=0.03, rtol=0.3, pace=TRANSIT)
    yield from hand.move(phase[0], standoff, Rg, OPEN, tol=0.01, rtol=0.05)
    yield from hand.pause(phase[0], OPEN)
    yield from hand.move(phase[0], grasp + 0.04 * out, Rg, OPEN, tol=0.01)
    yield from hand.move(phase[0], grasp, Rg, OPEN, tol=0.008)
    yield from hand.hold(phase[1], CLOSE, 15)
    yield from hand.pause(phase[1], CLOSE)
    # turn the lever down: carry grasp point and gripper round the latch axis (positive angle = tip down)
    p, _ = hand.pose()
    turn = 1.5
    for k in range(1, st.turn_steps + 1):
        Rl = Rotation.from_rotvec(latch_axis * turn * k / st.turn_steps).as_matrix()
        yield phase[2], hand.action(latch_anchor + Rl @ (p - latch_anchor), Rl @ Rg, CLOSE, speed=0.02)
    Rl = Rotation.from_rotvec(latch_axis * turn).as_matrix()
    p, Rt = latch_anchor + Rl @ (p - latch_anchor), Rl @ Rg
    yield from hand.hold(phase[2], CLOSE, 8, pos=p, R=Rt)
    # pull: carry grasp point and gripper round the door hinge until the door stands open
    angle = 0.0
    while angle < 0.6:
        angle += st.pull_speed
        Rh = Rotation.from_rotvec(hinge_axis * angle).as_matrix()
        yield phase[3], hand.action(hinge_anchor + Rh @ (p - hinge_anchor), Rh @ Rt, CLOSE, speed=0.02)
        if scenes.door_hinge(env) > 0.36:
            break
    yield from hand.pause(phase[3], CLOSE)
    # Let the lever turn back up while still holding it, then open and back off along the approach axis.
    # Opening with the lever turned down leaves a finger hooked on the bar: backing off then presses the door
    # into its soft hinge limit, and it springs shut when the finger slips free.
    p, R = hand.pose()
    anchor, axis = d.xanchor[latch].copy(), d.xaxis[latch].copy()
    turned = float(env.sim.data.qpos[env.sim.model.get_joint_qpos_addr("Door_latch_joint")])
    back_steps = max(20, st.turn_steps // 2)
    for k in range(1, back_steps + 1):
        Rl = Rotation.from_rotvec(-axis * turned * k / back_steps).as_matrix()
        yield phase[4], hand.action(anchor + Rl @ (p - anchor), Rl @ R, CLOSE, speed=0.02)
    yield from hand.hold(phase[4], OPEN, 12)
    p, R = hand.pose()
    yield from hand.move(phase[4], p - 0.10 * R[:, 2], R, OPEN, tol=0.01, max_steps=80)
    yield from hand.pause(phase[4], OPEN)


# ---------------------------------------------------------------------------------------------- PickPlace


def down_frame(u) -> np.ndarray:
    """Grip site pointing down, fingers closing along horizontal ``u``."""
    u = np.array([u[0], u[1], 0.0])
    u /= np.linalg.norm(u)
    z = np.array([0.0, 0.0, -1.0])
    return np.stack([u, np.cross(z, u), z], axis=1)


# Cereal box half-extents (m): thin axis (held between the fingers) 0.015, wide axis 0.05, height 0.075.
BOX_THIN, BOX_WIDE = 0.015, 0.05
DIVIDER_HALF = 0.01
CLEARANCE = 0.02


def compartment_target(env, index: int, jitter: float = 0.0) -> np.ndarray:
    """Where to set the box down in compartment ``index`` (robosuite's indexing).

    Near compartments take their centre. Far compartments (1, 3) are at the edge of the Panda's reach once
    the box is down on the floor, so the box goes just beyond the near/far divider, held with its thin side
    toward the divider (see ``pick_place_operator``). ``jitter`` (m) shifts the point along y."""
    b2, bs = env.bin2_pos, env.bin_size
    far, left = index in (1, 3), index >= 2
    x_lo = b2[0] - (0.0 if far else bs[0] / 2)
    y_lo = b2[1] - (0.0 if left else bs[1] / 2)
    x_hi, y_hi = x_lo + bs[0] / 2, y_lo + bs[1] / 2
    if not far:
        return np.array([(x_lo + x_hi) / 2, (y_lo + y_hi) / 2 + jitter])
    x = x_lo + DIVIDER_HALF + BOX_THIN + CLEARANCE
    margin = DIVIDER_HALF + BOX_WIDE + CLEARANCE
    y = np.clip((y_lo + y_hi) / 2 + jitter, y_lo + margin, y_hi - margin)
    if left:  # the far-left compartment is the farthest from the base: hug the middle divider
        y = y_lo + margin + abs(jitter) / 3
    return np.array([x, y])


def wrist_safe_axis(env, R_now: np.ndarray, daz: float, axis: np.ndarray) -> np.ndarray:
    """``axis`` or ``-axis`` as the finger-closing direction, whichever leaves joint 7 nearer the middle.

    The two grasps are the same (the gripper is symmetric) but differ by pi in joint 7, and one of them is past
    its limit (±2.9 rad). With the hand pointing down, joint 7 changes by the change of the arm's azimuth
    round the base (``daz``) minus the change of the fingers' yaw."""
    q7 = float(env.sim.data.qpos[env.robots[0].joint_indexes[6]])
    yaw_now = np.arctan2(R_now[1, 0], R_now[0, 0])
    best = None
    for u in (axis, -axis):
        dyaw = (np.arctan2(u[1], u[0]) - yaw_now + np.pi) % (2 * np.pi) - np.pi
        q7_after = abs(q7 + daz - dyaw)
        if best is None or q7_after < best[0]:
            best = (q7_after, u)
    return best[1]


def pick_place_operator(
    env, hand: Hand, bin_index: int, grasp_above: float = 0.04, measure_rest: bool = False
) -> Iterator[Step]:
    """Pick the object from the source bin and set it down in compartment ``bin_index``.

    ``grasp_above``: where the fingers close above the object's centre. ``measure_rest``: lower the object
    until its centre is where it stood in the source bin (the bins' floors are level), instead of the cereal
    box's standing height; the shipped episodes were recorded with the cereal box's."""
    import mujoco

    m, d = env.sim.model._model, env.sim.data._data
    obj = env.objects[env.object_id]
    body = env.obj_body_id[obj.name]
    geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, obj.name + "_g0")
    st = hand.style
    phase = scenes.bin_phases(bin_index)
    yield from hand.hold(phase[0], OPEN, 5)  # let the box settle
    home, _ = hand.pose()
    opos = d.xpos[body].copy()
    thin = d.geom_xmat[geom].reshape(3, 3)[:, 0].copy()  # the box's thin axis = finger closing direction
    _, R0 = hand.pose()
    u = thin if np.dot(thin[:2], R0[:2, 0]) >= 0 else -thin
    Rg = down_frame(u)
    top = 1.08 + st.height
    above = [opos[0] + st.lateral, opos[1] - st.lateral, top]
    yield from hand.move(phase[0], above, Rg, OPEN, tol=0.02, rtol=0.1, pace=TRANSIT)
    yield from hand.move(phase[0], [opos[0], opos[1], top], Rg, OPEN, tol=0.01)
    yield from hand.pause(phase[0], OPEN)
    opos = d.xpos[body].copy()
    rest_z = float(opos[2]) if measure_rest else None
    yield from hand.move(phase[1], [opos[0], opos[1], opos[2] + grasp_above], Rg, OPEN, tol=0.006, max_steps=160)
    yield from hand.hold(phase[2], CLOSE, 15)
    yield from hand.pause(phase[2], CLOSE)
    p, _ = hand.pose()
    yield from hand.move(phase[3], [p[0], p[1], top], Rg, CLOSE, tol=0.015)
    yield from hand.pause(phase[3], CLOSE)  # a look at the grip before carrying the box away
    tx, ty = compartment_target(env, bin_index, jitter=0.3 * st.lateral)
    base = env.sim.data.get_body_xpos(env.robots[0].robot_model.root_body)
    daz = np.arctan2(ty - base[1], tx - base[0]) - np.arctan2(p[1] - base[1], p[0] - base[0])
    if bin_index in (1, 3):
        # thin side toward the near/far divider: fingers closing along ±x, the box's wide side along y
        Rg = down_frame(wrist_safe_axis(env, Rg, daz, np.array([1.0, 0.0])))
    else:
        # turn the wrist with the change of azimuth round the base, keeping joint 7 where it is
        Rg = Rotation.from_rotvec([0, 0, daz]).as_matrix() @ Rg
    yield from hand.move(phase[4], [tx, ty, top], Rg, CLOSE, tol=0.015, max_steps=400, pace=TRANSIT)
    yield from hand.pause(phase[4], CLOSE)
    # lower until the box stands on the compartment floor (box centre ~0.895 m, half height 0.075), or until
    # the hand stops making progress (at the far compartments the arm can run out of reach a little early)
    p, _ = hand.pose()
    down_z, floor_z = (0.905, 0.90) if rest_z is None else (rest_z + 0.01, rest_z + 0.005)
    target = np.array([tx, ty, down_z + p[2] - d.xpos[body][2]])
    heights: list[float] = []
    for _ in range(200):
        heights.append(float(d.xpos[body][2]))
        stalled = len(heights) > 15 and heights[-16] - heights[-1] < 0.002
        if hand.error(target, Rg)[0] < 0.01 or heights[-1] < floor_z or stalled:
            break
        yield phase[5], hand.action(target, Rg, CLOSE)
    yield from hand.pause(phase[5], CLOSE)  # settle the box before letting go
    p, _ = hand.pose()
    yield from hand.hold(phase[6], OPEN, 15)
    yield from hand.move(phase[7], [p[0], p[1], top], Rg, OPEN, tol=0.015)
    # back to where the hand started: seen from above, the arm would otherwise hide the box it just placed
    yield from hand.move(phase[7], [home[0], home[1], top], Rg, OPEN, tol=0.02, rtol=0.2, pace=TRANSIT)
    yield from hand.pause(phase[7], OPEN)


# ---------------------------------------------------------------------------------------------- Stack


def cube_axis(env, body: int, R_now: np.ndarray) -> np.ndarray:
    """The red cube's horizontal face normal (x or y of its body frame) nearest the fingers' closing axis."""
    R = env.sim.data.body_xmat[body].reshape(3, 3)
    axes = [R[:, 0], R[:, 1]]
    return max(axes, key=lambda a: abs(float(np.dot(a[:2], R_now[:2, 0]))))


def stack_operator(env, hand: Hand, phases: tuple[str, ...], grasp_above: float = 0.0) -> Iterator[Step]:
    """Pick the red cube (robosuite's cubeA) and set it down on the green one (cubeB)."""
    d = env.sim.data
    a_body, b_body = env.cubeA_body_id, env.cubeB_body_id
    st = hand.style
    yield from hand.hold(phases[0], OPEN, 5)
    home, R0 = hand.pose()
    apos = d.body_xpos[a_body].copy()
    Rg = down_frame(wrist_safe_axis(env, R0, 0.0, cube_axis(env, a_body, R0)[:2]))
    top = apos[2] + 0.16 + st.height
    yield from hand.move(phases[0], [apos[0] + st.lateral, apos[1] - st.lateral, top], Rg, OPEN, tol=0.02, rtol=0.1)
    yield from hand.move(phases[0], [apos[0], apos[1], top], Rg, OPEN, tol=0.008)
    yield from hand.pause(phases[0], OPEN)
    apos = d.body_xpos[a_body].copy()
    yield from hand.move(phases[1], [apos[0], apos[1], apos[2] + grasp_above], Rg, OPEN, tol=0.005, max_steps=160)
    yield from hand.hold(phases[2], CLOSE, 15)
    yield from hand.pause(phases[2], CLOSE)
    p, _ = hand.pose()
    yield from hand.move(phases[3], [p[0], p[1], top], Rg, CLOSE, tol=0.015)
    yield from hand.pause(phases[3], CLOSE)
    bpos = d.body_xpos[b_body].copy()
    held = d.body_xpos[a_body] - hand.pose()[0]  # where the cube hangs from the grip site
    over = np.array([bpos[0] - held[0], bpos[1] - held[1], top])
    yield from hand.move(phases[4], over, Rg, CLOSE, tol=0.006, max_steps=400)
    yield from hand.pause(phases[4], CLOSE)
    # the red cube's centre 0.045 m above the green one's (half sizes 0.02 + 0.025) plus a few mm of air
    target = np.array([over[0], over[1], bpos[2] + 0.05 - held[2]])
    yield from hand.move(phases[5], target, Rg, CLOSE, tol=0.004, max_steps=200)
    yield from hand.pause(phases[5], CLOSE)
    yield from hand.hold(phases[6], OPEN, 15)
    p, _ = hand.pose()
    yield from hand.move(phases[7], [p[0], p[1], top], Rg, OPEN, tol=0.015)
    yield from hand.move(phases[7], [home[0], home[1], top], Rg, OPEN, tol=0.02, rtol=0.2, pace=TRANSIT)
    yield from hand.pause(phases[7], OPEN)
