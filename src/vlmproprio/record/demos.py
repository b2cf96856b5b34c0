"""Import human demonstrations from robosuite / robomimic ``demo.hdf5`` files as episodes.

File layouts read (both keep one group per demonstration under ``data``)::

    data                      attrs: env (robosuite) or env_args (robomimic: JSON with env_name, env_kwargs),
                                     env_info (robosuite: JSON with robots, controller_configs)
    data/<demo>               attrs: model_file (the MJCF XML the demo ran on)
    data/<demo>/states        (N, 1 + nq + nv) flattened MuJoCo states: time, qpos, qvel; states[t] is the
                              state before actions[t] (robosuite's gather drops the state after the last action)
    data/<demo>/actions       (N, 7) OSC_POSE actions

Each demo is loaded into the matching robosuite env from its own model XML (our
bin camera added for pick-and-place, see ``scenes.with_bin_camera``; the ghost
objects hidden), replayed, and observed with the recorder's own ``Tracer``: a
state row per step, a frame every 20 steps and one on the demo's last state
(the recorder rests until a sampled step instead; an imported demo has no steps
after its last state to show, and inventing some would be fabrication). The
episode is written by the recorder's ``build_episode``.

Replay, and how exact it is
---------------------------
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

Ground truth from simulator signals
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

Episode ids are ``<prefix>_<nn>`` (``imp_<task>`` by default, ``nn`` the demo's
number: ``demo_7`` -> ``imp_door_07``). ``seed`` is -1 (not a seeded recording);
``extra`` names the source file and demo, the replay mode and the outcome.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.episodes import (
    MANIFEST_NAME,
    check_episode_id,
    read_manifest,
    update_manifest,
    write_episode,
    write_manifest,
)
from vlmproprio.errors import VlmproprioError
from vlmproprio.record import scenes
from vlmproprio.record.recorder import HORIZON, Trace, Tracer, build_episode, prepare_robosuite

# CLI task names -> what the importer makes of them.
TASKS: dict[str, scenes.TaskInfo] = {
    "door": scenes.DOOR,
    "pick_place_cereal": scenes.PICK_PLACE,
    "pick_place_can": scenes.PICK_PLACE_CAN,
    "lift": scenes.LIFT,
}
SUPPORTED_ENVS = tuple(sorted(t.env_name for t in TASKS.values()))
REPLAY_MODES = ("auto", "actions", "states")
NO_SEED = -1

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


class DemoImportError(VlmproprioError):
    """A demo file that cannot be imported; the message names the file (and demo) and what is wrong."""


# ---------------------------------------------------------------------------------------------- file


@dataclass(frozen=True)
class DemoFile:
    """What a demo file says about itself."""

    path: Path
    env_name: str
    layout: str  # "robosuite" (env + env_info) | "robomimic" (env_args)
    env_kwargs: dict  # robots, controller_configs, control_freq... as recorded (may be empty)
    demos: tuple[str, ...]
    recorded_with: str | None  # robosuite version that wrote it, when the file says


@dataclass(frozen=True)
class Demo:
    name: str
    model_xml: str
    states: np.ndarray  # (N, 1 + nq + nv)
    actions: np.ndarray | None  # (N, action dim) or None


def _text(value) -> str:
    if isinstance(value, bytes | np.bytes_):
        return value.decode("utf-8")
    return str(value)


def _demo_key(name: str) -> tuple:
    m = re.search(r"(\d+)$", name)
    return (0, int(m.group(1)), name) if m else (1, 0, name)


def _h5py():
    try:
        import h5py
    except ImportError as exc:
        raise DemoImportError("reading demo files needs h5py: pip install 'vlmproprio[record]'") from exc
    return h5py


def _open(path: Path):
    h5py = _h5py()
    path = Path(path)
    if not path.is_file():
        raise DemoImportError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise DemoImportError(f"{path}: not a readable HDF5 file ({exc})") from exc


def _json_attr(path: Path, attrs, key: str) -> dict:
    try:
        data = json.loads(_text(attrs[key]))
    except ValueError as exc:
        raise DemoImportError(f"{path}: data.attrs[{key!r}] is not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise DemoImportError(f"{path}: data.attrs[{key!r}] must be a JSON object")
    return data


def read_demo_file(path: Path) -> DemoFile:
    """The environment and demo names of a robosuite or robomimic demo file."""
    h5py = _h5py()
    path = Path(path)
    with _open(path) as f:
        data = f.get("data")
        if not isinstance(data, h5py.Group):
            raise DemoImportError(f"{path}: no 'data' group (not a robosuite or robomimic demo file)")
        attrs = data.attrs
        if "env_args" in attrs:
            args = _json_attr(path, attrs, "env_args")
            env_name, layout = args.get("env_name"), "robomimic"
            kwargs = args.get("env_kwargs") or {}
            recorded_with = args.get("env_version")
        elif "env" in attrs:
            env_name, layout = _text(attrs["env"]), "robosuite"
            kwargs = _json_attr(path, attrs, "env_info") if "env_info" in attrs else {}
            recorded_with = _text(attrs["repository_version"]) if "repository_version" in attrs else None
        else:
            raise DemoImportError(f"{path}: data has neither an 'env' nor an 'env_args' attribute (which env is it?)")
        demos = tuple(
            sorted((k for k in data if isinstance(data[k], h5py.Group) and "states" in data[k]), key=_demo_key)
        )
    if not isinstance(env_name, str) or not env_name:
        raise DemoImportError(f"{path}: no environment name in the file")
    if not demos:
        raise DemoImportError(f"{path}: no demonstrations (no data/<demo>/states)")
    return DemoFile(path, env_name, layout, dict(kwargs), demos, None if recorded_with is None else str(recorded_with))


def read_demo(path: Path, name: str) -> Demo:
    path = Path(path)
    with _open(path) as f:
        grp = f.get(f"data/{name}")
        if grp is None:
            raise DemoImportError(f"{path}: no demo {name!r}")
        where = f"{path} {name}"
        if "model_file" not in grp.attrs:
            raise DemoImportError(f"{where}: no model_file attribute (the MJCF XML the demo ran on)")
        try:
            states = np.asarray(grp["states"][()], dtype=np.float64)
            actions = np.asarray(grp["actions"][()], dtype=np.float64) if "actions" in grp else None
        except (OSError, TypeError, ValueError) as exc:
            raise DemoImportError(f"{where}: cannot read states/actions ({exc})") from exc
        xml = _text(grp.attrs["model_file"])
    if states.ndim != 2 or len(states) < 2:
        raise DemoImportError(
            f"{where}: states must be a (steps, state size) array of 2 or more steps, got {states.shape}"
        )
    if not np.isfinite(states).all():
        raise DemoImportError(f"{where}: non-finite values in states")
    if actions is not None and (actions.ndim != 2 or len(actions) < len(states) - 1):
        actions = None  # unusable for an action replay; the recorded states are still complete
    return Demo(name, xml, states, actions)


def task_for(file: DemoFile, task: str | None) -> tuple[str, scenes.TaskInfo]:
    """The importer task for a file: the one asked for, which must match the file's env, or the file's own."""
    by_env = {info.env_name: name for name, info in TASKS.items()}
    if task is not None and task not in TASKS:
        raise DemoImportError(f"unknown task {task!r} (supported: {', '.join(TASKS)})")
    if file.env_name not in by_env:
        raise DemoImportError(
            f"{file.path}: environment {file.env_name!r} is not supported (supported: {', '.join(SUPPORTED_ENVS)})"
        )
    if task is not None and TASKS[task].env_name != file.env_name:
        raise DemoImportError(
            f"{file.path}: the demos are of {file.env_name}, but --task {task} expects {TASKS[task].env_name} "
            f"(use --task {by_env[file.env_name]})"
        )
    robots = _robots(file)
    if robots != ["Panda"]:
        raise DemoImportError(
            f"{file.path}: recorded with robots {robots}; episodes hold the Panda's state (7 joints + gripper)"
        )
    name = by_env[file.env_name]
    return name, TASKS[name]


# ---------------------------------------------------------------------------------------------- env


def _robots(file: DemoFile) -> list[str]:
    robots = file.env_kwargs.get("robots", ["Panda"])
    return [robots] if isinstance(robots, str) else list(robots)


def make_import_env(file: DemoFile, task: scenes.TaskInfo, horizon: int):
    """A robosuite env of the demo's class, with its recorded controller and control rate where possible.

    Returns (env, note): note says when the recorded controller could not be used (the default OSC_POSE
    is, and an action replay then cannot be exact; ``auto`` falls back to the recorded states)."""
    import robosuite as suite

    kwargs = scenes.env_kwargs(seed=0, horizon=horizon)
    if "control_freq" in file.env_kwargs:
        kwargs["control_freq"] = file.env_kwargs["control_freq"]
    controller = file.env_kwargs.get("controller_configs")
    if controller:
        try:
            return suite.make(task.env_name, controller_configs=controller, **kwargs), None
        except Exception as exc:  # any malformed or version-specific controller config: fall back below
            note = f"recorded controller not loadable here ({type(exc).__name__}: {str(exc)[:120]}); default used"
            return suite.make(task.env_name, **kwargs), note
    return suite.make(task.env_name, **kwargs), None


def load_demo_model(env, demo: Demo, file: DemoFile, camera: str) -> None:
    """Reset ``env`` onto the demo's model at its first state, as robosuite's DataCollectionWrapper does."""
    where = f"{file.path} {demo.name}"
    try:
        env.reset_from_xml_string(demo.model_xml)
    except Exception as exc:  # parse / compile / reference errors from robosuite and MuJoCo
        raise DemoImportError(
            f"{where}: robosuite could not load the demo's model ({type(exc).__name__}: {str(exc)[:200]}); "
            f"was it recorded with another robosuite version?"
        ) from exc
    m = env.sim.model
    size = 1 + m.nq + m.nv
    if demo.states.shape[1] != size:
        raise DemoImportError(
            f"{where}: states have {demo.states.shape[1]} columns, the model needs {size} (time, qpos, qvel)"
        )
    if camera not in m.camera_names:
        raise DemoImportError(f"{where}: no camera {camera!r} in the model (cameras: {', '.join(m.camera_names)})")
    env.sim.reset()
    env.sim.set_state_from_flattened(demo.states[0])
    env.sim.forward()
    scenes.hide_ghosts(env)


# ---------------------------------------------------------------------------------------------- replay


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


# ---------------------------------------------------------------------------------------------- ground truth


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


# ---------------------------------------------------------------------------------------------- import


def episode_id_for(prefix: str, demo_name: str, position: int) -> str:
    m = re.search(r"(\d+)$", demo_name)
    suffix = f"{int(m.group(1)):02d}" if m else re.sub(r"[^a-z0-9_-]", "-", demo_name.lower()) or f"{position:02d}"
    return check_episode_id(f"{prefix}_{suffix}")


def _outcome(env, task: scenes.TaskInfo) -> tuple[int | None, bool, dict]:
    """(target compartment, success, extra) from the final state."""
    if task.task == "door":
        return None, scenes.door_success(env), {"door_hinge_rad": round(scenes.door_hinge(env), 4)}
    pos = scenes.object_pos(env)
    extra = {"object_pos": [round(float(v), 4) for v in pos]}
    if task.task == "lift":
        return None, bool(env._check_success()), extra
    inside = [scenes.in_compartment(env, k) for k in range(4)]
    extra["in_compartments"] = inside
    if any(inside):
        return inside.index(True), True, extra
    return int(env.object_id), False, extra


class ImportEnv:
    """One robosuite env for the demos of a file, reloaded from each demo's model XML as robosuite's
    DataCollectionWrapper did between the demos it collected (a reload rebuilds the sim, the controllers and
    the observables' clock, so a demo's replay does not depend on the demos before it)."""

    def __init__(self, file: DemoFile, task: scenes.TaskInfo, camera: str):
        try:
            prepare_robosuite()
        except ImportError as exc:
            raise DemoImportError(
                f"importing demos needs robosuite and mujoco ({exc}): pip install 'vlmproprio[record]'"
            ) from exc
        self.file, self.task, self.camera = file, task, camera
        self.env, self.controller_note = make_import_env(file, task, horizon=HORIZON)
        if camera == scenes.BIN_CAMERA:
            # after robosuite's own processor (edit_model_xml: asset paths), whenever the env loads an XML
            self.env.set_xml_processor(scenes.with_bin_camera)

    def close(self) -> None:
        self.env.close()

    def __enter__(self) -> ImportEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def import_demo(
    file: DemoFile,
    demo: Demo,
    task: scenes.TaskInfo,
    episode_id: str,
    camera: str | None = None,
    replay_mode: str = "auto",
    env: ImportEnv | None = None,
) -> dict:
    """Replay one demo and build its episode (not written). Returns a summary dict with meta, images, states.

    ``env``: an ImportEnv for the file to reuse (its camera wins); by default one is made and closed."""
    t0 = time.perf_counter()
    own = env is None
    ie = ImportEnv(file, task, camera or task.camera) if own else env
    camera, controller_note = ie.camera, ie.controller_note
    where = f"{file.path} {demo.name}"
    try:
        load_demo_model(ie.env, demo, file, camera)
        rep = replay(ie.env, demo, task, camera, replay_mode, where)
        target, success, outcome = _outcome(ie.env, task)
        # the rubric reads image words (left/right, top/bottom) in this camera's terms
        axes = scenes.camera_axes(ie.env, camera)
    finally:
        if own:
            ie.close()
    trace = rep.trace
    opening = np.array(trace.joints)[:, 7]
    if task.task == "door":
        phases = door_phases(opening, trace.signal("latch"), trace.signal("hinge"))
        phase_names = scenes.DOOR_PHASES
    elif task.task == "lift":
        phase_names = scenes.LIFT_PHASES
        phases = pick_phases(opening, trace.signal("grip"), trace.signal("object"), phase_names, transport=False)
    else:
        phase_names = scenes.bin_phases(target)
        phases = pick_phases(opening, trace.signal("grip"), trace.signal("object"), phase_names, transport=True)
    extra = {
        "source": {
            "file": file.path.name,
            "demo": demo.name,
            "layout": file.layout,
            "recorded_with_robosuite": file.recorded_with,
            "demo_states": len(demo.states),
        },
        "replay": rep.mode,
        **rep.notes,
        **({"controller": controller_note} if controller_note else {}),
        "ground_truth": "phases from simulator signals (vlmproprio.record.demos)",
        "camera_axes": axes,
        **outcome,
    }
    meta, states = build_episode(
        trace,
        phases,
        phase_names,
        episode_id=episode_id,
        task=task,
        instruction=scenes.instruction(task, target),
        target_bin=scenes.target_bin(target) if target is not None else None,
        seed=NO_SEED,
        success=success,
        extra=extra,
        camera=camera,
    )
    return {
        "episode_id": episode_id,
        "demo": demo.name,
        "steps": meta["steps"],
        "frames": len(trace.images),
        "replay": rep.mode,
        "wall_s": time.perf_counter() - t0,
        "meta": meta,
        "images": trace.images,
        "states": states,
        "trace": trace,
    }


def _write_manifest(out_root: Path, episode_ids: Sequence[str]) -> None:
    """Re-hash only the imported episodes when a manifest exists (other episodes keep what was blessed)."""
    if not (out_root / MANIFEST_NAME).is_file():
        write_manifest(out_root)
        return
    prefixes = tuple(f"episodes/{eid}/" for eid in episode_ids)
    old = [k for k in read_manifest(out_root) if k.startswith(prefixes)]
    new = [p.relative_to(out_root).as_posix() for eid in episode_ids for p in (out_root / "episodes" / eid).rglob("*")]
    update_manifest(out_root, sorted(set(old) | {p for p in new if (out_root / p).is_file()}))


def import_demos(
    path: Path,
    out_root: Path,
    task: str | None = None,
    *,
    camera: str | None = None,
    demos: Sequence[str] | None = None,
    replay_mode: str = "auto",
    prefix: str | None = None,
    progress: bool = True,
) -> list[dict]:
    """Import demos of a file (default: all) as episodes under ``out_root`` and update its manifest."""
    file = read_demo_file(path)
    task_name, info = task_for(file, task)
    names = list(demos) if demos else list(file.demos)
    missing = [n for n in names if n not in file.demos]
    if missing:
        raise DemoImportError(f"{file.path}: no demo {', '.join(missing)} (demos: {', '.join(file.demos)})")
    prefix = prefix or f"imp_{task_name}"
    ids = [episode_id_for(prefix, n, i) for i, n in enumerate(names)]
    if len(set(ids)) != len(ids):
        raise DemoImportError(f"{file.path}: demo names {names} give duplicate episode ids {ids}")
    if replay_mode not in REPLAY_MODES:
        raise DemoImportError(f"unknown replay mode {replay_mode!r} (choose from {', '.join(REPLAY_MODES)})")
    out_root = Path(out_root)
    results = []
    it = zip(names, ids, strict=True)
    if progress:
        from tqdm import tqdm

        it = tqdm(list(it), desc="importing", unit="demo")
    with ImportEnv(file, info, camera or info.camera) as env:
        for name, eid in it:
            res = import_demo(file, read_demo(file.path, name), info, eid, replay_mode=replay_mode, env=env)
            write_episode(out_root, res["meta"], res["images"], res["states"])
            results.append(res)
    _write_manifest(out_root, ids)
    return results
