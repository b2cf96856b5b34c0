"""Record episodes: run a scripted operator in robosuite, sample frames, derive ground truth, write fixtures.

Rendering uses MuJoCo's headless backend: ``MUJOCO_GL`` is set to ``egl`` unless
the caller chose one (``osmesa`` gives bit-identical frames, more slowly).
A new env per episode, a seed passed to robosuite and seeded operators make
recording bit-identical across processes on this machine kind (pinned mujoco).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlmproprio.episodes import (
    PhaseSpan,
    StepStates,
    TargetBin,
    episode_metadata,
    pixel_sha256,
    standard_episode_ids,
    write_episode,
    write_manifest,
)
from vlmproprio.errors import VlmproprioError
from vlmproprio.primitives import direction_label
from vlmproprio.record import scenes

# No episode may run longer than this (the paper's longest are well under it).
HORIZON = 1400
# Ground-truth direction at step t: displacement of the grip site over [t - W, t + W] (one frame interval).
DIRECTION_HALF_WINDOW = scenes.STEP_STRIDE // 2


class RecordingError(VlmproprioError):
    """An episode could not be recorded as required (the operator failed the task, rendering failed...)."""


@dataclass(frozen=True)
class EpisodeSpec:
    episode_id: str
    task: scenes.TaskInfo
    seed: int
    bin_index: int | None = None


def episode_spec(episode_id: str) -> EpisodeSpec:
    """door_SS -> Door with seed SS; binK_SS -> PickPlaceCereal into compartment K with seed 100 + 10K + SS."""
    try:
        if episode_id.startswith("door_"):
            return EpisodeSpec(episode_id, scenes.DOOR, int(episode_id[5:]))
        if episode_id.startswith("bin") and episode_id[4] == "_":
            k, s = int(episode_id[3]), int(episode_id[5:])
            if 0 <= k <= 3:
                return EpisodeSpec(episode_id, scenes.PICK_PLACE, 100 + 10 * k + s, k)
    except (ValueError, IndexError):
        pass
    raise RecordingError(f"cannot record {episode_id!r}: ids look like door_07 or bin2_01 (bin index 0-3)")


def prepare_robosuite() -> None:
    """Headless rendering, and robosuite's per-env INFO lines kept off the progress bar."""
    import logging

    os.environ.setdefault("MUJOCO_GL", "egl")
    if os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    import robosuite  # noqa: F401 - its import installs the logger whose level we lower

    logging.getLogger("robosuite_logs").setLevel(logging.WARNING)


def versions() -> dict[str, str]:
    import mujoco
    import robosuite

    import vlmproprio

    return {"robosuite": robosuite.__version__, "mujoco": mujoco.__version__, "vlmproprio": vlmproprio.__version__}


def _rpy(quats_xyzw: np.ndarray) -> np.ndarray:
    """Extrinsic x-y-z Euler angles, unwrapped along the episode so roll near ±pi never jumps."""
    from scipy.spatial.transform import Rotation

    return np.unwrap(Rotation.from_quat(quats_xyzw).as_euler("xyz"), axis=0)


def _state_row(obs: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    q = obs["robot0_joint_pos"]
    fingers = obs["robot0_gripper_qpos"]
    joints = np.append(q, fingers[0] - fingers[1])  # finger opening in m
    return joints, obs["robot0_eef_pos"].copy(), obs["robot0_eef_quat"].copy()


def _directions(ee_pos: np.ndarray) -> list[str]:
    T = len(ee_pos)
    out = []
    for t in range(T):
        a, b = max(0, t - DIRECTION_HALF_WINDOW), min(T - 1, t + DIRECTION_HALF_WINDOW)
        out.append(direction_label(ee_pos[b] - ee_pos[a]))
    return out


def _phase_spans(phases: Sequence[str]) -> list[PhaseSpan]:
    spans: list[PhaseSpan] = []
    start = 0
    for t in range(1, len(phases) + 1):
        if t == len(phases) or phases[t] != phases[start]:
            spans.append(PhaseSpan(phases[start], start, t - 1))
            start = t
    return spans


# ---------------------------------------------------------------------------------------------- trace


@dataclass
class Trace:
    """What a recording sees of one episode: a state row per sim step, a frame on sampled steps, and per-step
    simulator signals (object position, door angles...) for the ground truth."""

    joints: list[np.ndarray] = field(default_factory=list)
    pos: list[np.ndarray] = field(default_factory=list)
    quats: list[np.ndarray] = field(default_factory=list)
    signals: list[dict[str, np.ndarray | float]] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)
    frame_steps: list[int] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.joints)

    def signal(self, name: str) -> np.ndarray:
        return np.array([s[name] for s in self.signals])


class Tracer:
    """Builds a Trace from a robosuite env, the one way both the recorder and the demo importer observe a step.

    A row is robosuite's observation as ``env.step`` returns it. robosuite samples observables on a clock
    that ``reset()`` restarts and every forced update advances by one physics substep; with the one forced
    update of ``start()`` after a reset, ``env.step`` reports the joints after the 24th of its 25 substeps
    and the end-effector pose computed before that substep. ``start()`` must therefore be the only forced
    update between the env's last reset and its first step, as it always was for the recorder."""

    def __init__(self, env, camera: str, signals: Callable[[object], dict] | None = None):
        self.env, self.camera, self._signals = env, camera, signals
        self.trace = Trace()
        self.obs: dict | None = None

    def start(self) -> None:
        self.obs = self.env._get_observations(force_update=True)

    def observe(self, obs: dict | None = None, frame: bool = False) -> bool:
        """Append the current step's row (from ``obs`` when given, else the last observation); render a frame
        on every STEP_STRIDE-th step, or when ``frame``. Returns whether a frame was rendered."""
        tr = self.trace
        step = len(tr)
        j, p, q = _state_row(self.obs if obs is None else obs)
        tr.joints.append(j)
        tr.pos.append(p)
        tr.quats.append(q)
        if self._signals is not None:
            tr.signals.append(self._signals(self.env))
        if step % scenes.STEP_STRIDE == 0 or frame:
            tr.images.append(scenes.render(self.env, self.camera))
            tr.frame_steps.append(step)
            return True
        return False

    def step(self, action: np.ndarray) -> None:
        self.obs, _, _, _ = self.env.step(action)


def build_episode(
    trace: Trace,
    phases: Sequence[str],
    phase_names: Sequence[str],
    *,
    episode_id: str,
    task: scenes.TaskInfo,
    instruction: str,
    target_bin: TargetBin | None,
    seed: int,
    success: bool,
    extra: dict,
    camera: str | None = None,
) -> tuple[dict, StepStates]:
    """Episode metadata and full-rate states from a trace and its per-step phase names (the one path from a
    trace to an episode, shared by the recorder and the demo importer)."""
    for i, img in enumerate(trace.images):
        if img.std() < 1.0:
            raise RecordingError(f"{episode_id}: frame {i} is blank (offscreen rendering failed?)")
    joints_a = np.array(trace.joints)
    ee_a = np.concatenate([np.array(trace.pos), _rpy(np.array(trace.quats))], axis=1)
    directions = _directions(ee_a[:, :3])
    direction_vocab = sorted(set(directions))
    steps = len(phases) - 1
    frame_rows = []
    for i, s in enumerate(trace.frame_steps):
        frame_rows.append(
            {
                "index": i,
                "step": s,
                "file": f"frames/{i:03d}.png",
                "pixel_sha256": pixel_sha256(trace.images[i]),
                "joints": joints_a[s].tolist(),
                "ee": ee_a[s].tolist(),
                "phase": phases[s],
                "direction": directions[s],
            }
        )
    states = StepStates(
        step=np.arange(len(phases), dtype=np.int32),
        joints=joints_a,
        ee=ee_a,
        phase=np.array([list(phase_names).index(p) for p in phases], dtype=np.int16),
        direction=np.array([direction_vocab.index(d) for d in directions], dtype=np.int16),
    )
    meta = episode_metadata(
        episode_id=episode_id,
        task=task.task,
        env_name=task.env_name,
        target_object=task.target_object,
        action=task.action,
        instruction=instruction,
        target_bin=target_bin,
        seed=seed,
        steps=steps,
        stride=scenes.STEP_STRIDE,
        camera=camera or task.camera,
        image_size=(scenes.IMAGE_SIZE, scenes.IMAGE_SIZE),
        versions=versions(),
        success=success,
        phase_names=phase_names,
        direction_vocab=direction_vocab,
        phases=_phase_spans(phases),
        frame_rows=frame_rows,
        extra=extra,
    )
    return meta, states


# ---------------------------------------------------------------------------------------------- record


def _object_signal(env) -> dict:
    return {"object": scenes.object_pos(env)}


@dataclass
class PolicyRun:
    trace: Trace
    phases: list[str]  # per step
    actions: list[np.ndarray]  # per step but the last
    cut: bool  # stopped by max_steps before the policy finished


def run_policy(
    env,
    policy: Iterable[tuple[str, np.ndarray]],
    camera: str,
    signals: Callable[[object], dict] | None = None,
    max_steps: int | None = None,
    episode_id: str = "",
) -> PolicyRun:
    """Drive a freshly reset env with a policy of (phase, action) pairs and trace it, then rest with the gripper
    open until the next sampled step so that the last frame shows the finished task. ``max_steps`` cuts the
    policy short (tests)."""
    from vlmproprio.record.operators import OPEN

    tracer = Tracer(env, camera, signals)
    tracer.start()
    phases: list[str] = []
    actions: list[np.ndarray] = []
    cut = False
    for phase, action in policy:
        step = len(phases)
        tracer.observe()
        phases.append(phase)
        tracer.step(action)
        actions.append(action)
        if step + 1 >= HORIZON:
            raise RecordingError(f"{episode_id}: operator still busy after {HORIZON} steps")
        if max_steps is not None and step + 1 >= max_steps:
            cut = True
            break
    last = phases[-1]
    rest = np.zeros(7) + np.array([0, 0, 0, 0, 0, 0, OPEN])
    while True:
        phases.append(last)
        if tracer.observe():
            break
        tracer.step(rest)
        actions.append(rest)
    return PolicyRun(tracer.trace, phases, actions, cut)


def operator_policy(env, spec: EpisodeSpec) -> tuple[Iterable[tuple[str, np.ndarray]], tuple[str, ...]]:
    """The scripted operator of an episode (seeded by its spec) and its phase names."""
    from vlmproprio.record import operators

    rng = np.random.default_rng(spec.seed)
    hand = operators.Hand(env, operators.Style.sample(rng), rng)
    if spec.task.task == "door":
        return operators.door_operator(env, hand), scenes.DOOR_PHASES
    return operators.pick_place_operator(env, hand, spec.bin_index), scenes.bin_phases(spec.bin_index)


def record_episode(spec: EpisodeSpec, out_root: Path | None = None) -> dict:
    """Run one episode; write it under ``out_root/episodes/`` when given. Returns a summary dict.

    Raises RecordingError when the operator does not really succeed (the fixture set must not contain a
    failed demonstration)."""
    prepare_robosuite()
    t0 = time.perf_counter()
    env = scenes.make_env(spec.task, spec.seed, HORIZON)
    try:
        policy, phase_names = operator_policy(env, spec)
        signals = _object_signal if spec.task.task == "pick_place" else None
        run = run_policy(env, policy, spec.task.camera, signals, episode_id=spec.episode_id)
        trace = run.trace
        if spec.task.task == "door":
            success = scenes.door_success(env)
            extra = {"door_hinge_rad": round(scenes.door_hinge(env), 4)}
        else:
            obj_track = trace.signal("object")
            moved = float(np.linalg.norm(obj_track[-1] - obj_track[-scenes.STEP_STRIDE - 1]))
            success = scenes.bin_success(env, spec.bin_index, moved)
            extra = {
                "object_pos": [round(float(v), 4) for v in scenes.object_pos(env)],
                "in_compartments": [scenes.in_compartment(env, k) for k in range(4)],
            }
    finally:
        env.close()
    if not success:
        raise RecordingError(f"{spec.episode_id} (seed {spec.seed}): the operator did not complete the task ({extra})")

    wall = time.perf_counter() - t0
    meta, states = build_episode(
        trace,
        run.phases,
        phase_names,
        episode_id=spec.episode_id,
        task=spec.task,
        instruction=scenes.instruction(spec.task, spec.bin_index),
        target_bin=scenes.target_bin(spec.bin_index) if spec.bin_index is not None else None,
        seed=spec.seed,
        success=success,
        extra=extra,
    )
    if out_root is not None:
        write_episode(Path(out_root), meta, trace.images, states)
    return {
        "episode_id": spec.episode_id,
        "steps": meta["steps"],
        "frames": len(trace.images),
        "wall_s": wall,
        "meta": meta,
        "images": trace.images,
    }


def record_all(
    out_root: Path, episode_ids: Iterable[str] | None = None, contact_sheets: Path | None = None
) -> list[dict]:
    """Record episodes (default: the standard 22) into ``out_root``, rewrite its manifest, print a summary.

    Contact sheets (all frames of an episode on one image, for checking by eye) go to ``contact_sheets``."""
    from tqdm import tqdm

    ids = list(episode_ids) if episode_ids else standard_episode_ids()
    specs = [episode_spec(eid) for eid in ids]
    out_root = Path(out_root)
    results = []
    t0 = time.perf_counter()
    bar = tqdm(specs, desc="recording", unit="episode")
    for spec in bar:
        bar.set_postfix_str(spec.episode_id)
        res = record_episode(spec, out_root)
        results.append(res)
        if contact_sheets is not None:
            from vlmproprio.record.contact_sheet import write_contact_sheet

            write_contact_sheet(Path(contact_sheets) / f"{spec.episode_id}.png", res["images"], res["meta"])
    write_manifest(out_root)
    total = time.perf_counter() - t0
    for task in ("door", "pick_place"):
        rs = [r for r in results if r["meta"]["task"] == task]
        if rs:
            print(
                f"{task}: {len(rs)} episodes, mean {np.mean([r['steps'] for r in rs]):.1f} steps "
                f"(min {min(r['steps'] for r in rs)}, max {max(r['steps'] for r in rs)}), "
                f"mean {np.mean([r['frames'] for r in rs]):.1f} frames"
            )
    print(f"recorded {len(results)} episodes in {total:.1f} s")
    return results
