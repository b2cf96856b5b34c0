"""Replaying a demo in its env, observed with the recorder's own ``Tracer``, and how exact it is.

Two things make a replay of recorded states differ from what the recorder sees
live, both found by comparing against recordings made in the same run:

* robosuite's ``env.step`` runs 25 physics substeps and reports observables
  sampled on a clock that ``reset()`` restarts: after the recorder's start
  that is the joints after substep 24 and the end-effector pose computed at
  substep 23 (``Tracer``). The recorded state is the one after substep 25.
* after ``mj_step`` the kinematics in ``MjData`` (body, site and geom poses,
  which ``sim.render`` draws) are those computed before the last integration,
  i.e. at substep 24.

Hence two replay modes (``--replay``):

* ``actions``: reset to ``states[0]``, step the env with the demo's actions and
  check every resulting state against the recorded one bit for bit. When all
  match, the observations and frames are exactly what the recorder would have
  recorded had it watched the demo. This needs the same robosuite, MuJoCo and
  controller the demo was collected with.
* ``states``: set each recorded state and reconstruct the substep-24 state by
  integrating the positions back one substep (``mj_integratePos`` with -dt,
  checked by integrating forward again): frames and joint rows are then
  bit-identical to the recorder's; the end-effector pose needs the substep-23
  positions, whose velocity is not recorded, so it is integrated back one more
  substep with the final velocity (error ~ dt^2 x joint acceleration, measured
  below 1e-5 m in the tests). Free joints (the objects) are integrated back
  through a normalised quaternion, which need not round-trip to the last bit.
* ``auto`` (default): ``actions`` when the file has actions and the replay
  reproduces every recorded state, else ``states`` (e.g. robomimic's datasets
  collected with older robosuite / mujoco-py versions).

robosuite's DataCollectionWrapper reloads the env from ``sim.model.get_xml()``
at every reset; MuJoCo 3.3.7 writes that XML with 6 significant digits (an
armature of 5/6 becomes 0.833333), so a demo never runs on exactly the model a
fresh env compiles, and a recording made with ``scenes.make_env`` and the same
actions diverges from it. The equality that holds, and that the tests check, is
with a recording made in the env the demo was collected in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vlmproprio.record import scenes
from vlmproprio.record.demos.files import Demo, DemoImportError
from vlmproprio.record.recorder import Trace, Tracer

REPLAY_MODES = ("auto", "actions", "states")


@dataclass
class Replay:
    trace: Trace
    mode: str  # "actions" | "states"
    notes: dict = field(default_factory=dict)


def _signals(task: scenes.TaskInfo):
    if task.task == "door":
        return lambda env: {"hinge": scenes.door_hinge(env), "latch": scenes.door_latch(env)}
    return lambda env: {"object": scenes.object_pos(env), "grip": scenes.grip_pos(env)}


def replay_actions(env, demo: Demo, task: scenes.TaskInfo, camera: str) -> tuple[Replay | None, int]:
    """Step the env with the demo's actions from its first state, as the recorder would have seen the demo.

    Returns (replay, n): replay is None when the state after step n differs from the recorded one."""
    n = len(demo.states)
    tracer = Tracer(env, camera, _signals(task))
    tracer.start()
    for t in range(n):
        if t:
            tracer.step(demo.actions[t - 1])
            if not np.array_equal(env.sim.get_state().flatten(), demo.states[t]):
                return None, t
        tracer.observe(frame=t == n - 1)
    return Replay(tracer.trace, "actions"), n


def replay_states(env, demo: Demo, task: scenes.TaskInfo, camera: str) -> Replay:
    """Set each recorded state and rebuild what ``env.step`` would have left in MjData (module docstring)."""
    import mujoco

    m, d = env.sim.model._model, env.sim.data._data
    h = m.opt.timestep
    n = len(demo.states)
    tracer = Tracer(env, camera, _signals(task))
    # Free joints (the objects) are integrated through a normalised quaternion that never round-trips to the
    # last bit, harmlessly; the check counts steps where a hinge or slide coordinate (the robot's) does not.
    hinged = np.zeros(m.nq, dtype=bool)
    for j in range(m.njnt):
        if m.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            hinged[m.jnt_qposadr[j]] = True
    inexact = 0
    for t, state in enumerate(demo.states):
        env.sim.set_state_from_flattened(state)
        if t == 0:  # the first state comes from a reset: its kinematics are fresh, as the recorder's
            env.sim.forward()
            obs = env._get_observations(force_update=True)
        else:
            q_end, v = d.qpos.copy(), d.qvel.copy()
            q24 = q_end.copy()
            mujoco.mj_integratePos(m, q24, v, -h)
            check = q24.copy()
            mujoco.mj_integratePos(m, check, v, h)
            inexact += not np.array_equal(check[hinged], q_end[hinged])
            q23 = q24.copy()
            mujoco.mj_integratePos(m, q23, v, -h)  # substep-24 velocity unknown: the final one stands in
            d.qpos[:] = q23
            mujoco.mj_forward(m, d)
            d.qpos[:] = q24
            obs = env._get_observations(force_update=True)  # joints at substep 24, pose computed at 23
            mujoco.mj_forward(m, d)  # substep-24 kinematics: what the frame and the signals see
            d.qpos[:] = q_end
        tracer.observe(obs, frame=t == n - 1)
    return Replay(tracer.trace, "states", {"steps_not_reversible": inexact})


def replay(env, demo: Demo, task: scenes.TaskInfo, camera: str, mode: str, where: str) -> Replay:
    if mode not in REPLAY_MODES:
        raise DemoImportError(f"unknown replay mode {mode!r} (choose from {', '.join(REPLAY_MODES)})")
    actions_fit = demo.actions is not None and demo.actions.shape[1] == env.action_dim
    if mode in ("auto", "actions") and actions_fit:
        result, t = replay_actions(env, demo, task, camera)
        if result is not None:
            return result
        if mode == "actions":
            raise DemoImportError(
                f"{where}: replaying the actions does not reproduce the recorded state at step {t} "
                "(other robosuite/MuJoCo version or controller?); use --replay states"
            )
        env.sim.reset()
        rep = replay_states(env, demo, task, camera)
        rep.notes["actions_diverged_at_step"] = t
        return rep
    if mode == "actions":
        raise DemoImportError(
            f"{where}: the file has no usable actions (none, too few, or not {env.action_dim} per step); "
            "use --replay states"
        )
    return replay_states(env, demo, task, camera)
