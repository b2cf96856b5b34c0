"""Record one slot of a new episode set: its scene and operator drawn from the episode's seed, its ground truth
from simulator signals, the seeds its operator failed on (and why) kept in the episode.

An attempt writes nothing: the episode is written once an attempt succeeds (``vlmproprio.record.sets``
writes it into a temporary folder and renames it into place).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from vlmproprio.record import families, scenes
from vlmproprio.record.catalog import SlotPlan
from vlmproprio.record.recorder import HORIZON, RecordingError, build_episode, prepare_robosuite, run_policy


@dataclass
class Recorded:
    """One slot's episode (metadata, frames, states) and the seeds that failed before it."""

    meta: dict
    images: list
    states: object
    skipped: list[dict] = field(default_factory=list)
    wall_s: float = 0.0


def _policy(env, plan: SlotPlan, rng: np.random.Generator):
    from vlmproprio.record import operators

    hand = operators.Hand(env, operators.Style.sample(rng), rng)
    op = plan.family.operator
    if op == "door":
        return operators.door_operator(env, hand), scenes.DOOR_PHASES, hand.style
    if op == "pick_place":
        policy = operators.pick_place_operator(env, hand, plan.bin_index, plan.obj.grasp_above_m, measure_rest=True)
        return policy, scenes.bin_phases(plan.bin_index), hand.style
    if op == "stack":
        return (
            operators.stack_operator(env, hand, families.STACK_PHASES, plan.obj.grasp_above_m),
            (families.STACK_PHASES),
            hand.style,
        )
    raise RecordingError(f"catalog task {plan.family.task!r}: no scripted operator {op!r}")


def _outcome(env, plan: SlotPlan, trace, cut: bool) -> tuple[bool, dict]:
    """(success, extra) of an attempt from the simulator's final state; a cut run (tests) is not judged."""
    task = plan.family.task
    extra: dict = {}
    moved = 0.0
    if task != "door":
        track = trace.signal("object")
        moved = float(np.linalg.norm(track[-1] - track[-scenes.STEP_STRIDE - 1])) if len(track) > 20 else 0.0
        extra["object_pos"] = [round(float(v), 4) for v in families.tracked_object(env, plan)]
    if task == "door":
        extra["door_hinge_rad"] = round(scenes.door_hinge(env), 4)
        success = scenes.door_success(env)
    elif task == "pick_place":
        extra["in_compartments"] = [scenes.in_compartment(env, k) for k in range(4)]
        success = scenes.bin_success(env, plan.bin_index, moved)
    else:
        extra["under_object_pos"] = [round(float(v), 4) for v in families.cube_pos(env, "cubeB")]
        success = families.stack_success(env, moved)
    return (False if cut else success), extra


def _scene(env, plan: SlotPlan) -> dict:
    """The drawn scene, for people reading the episode: where the object (or the door handle) starts."""
    if plan.family.task == "door":
        handle = env.sim.data.site_xpos[env.sim.model.site_name2id("Door_handle")]
        return {"handle_pos": [round(float(v), 4) for v in handle]}
    return {"object_start": [round(float(v), 4) for v in families.tracked_object(env, plan)]}


def attempt(plan: SlotPlan, seed: int, max_steps: int | None = None) -> Recorded:
    """One attempt of a slot with one seed; RecordingError when the operator fails the task."""
    prepare_robosuite()
    t0 = time.perf_counter()
    env = families.make_env(plan, seed, HORIZON)
    try:
        scene = _scene(env, plan)
        camera_axes = scenes.camera_axes(env, plan.family.camera)
        policy, phase_names, style = _policy(env, plan, np.random.default_rng(seed))
        signals = None if plan.family.task == "door" else (lambda e: {"object": families.tracked_object(e, plan)})
        run = run_policy(env, policy, plan.family.camera, signals, max_steps=max_steps, episode_id=plan.episode_id)
        success, extra = _outcome(env, plan, run.trace, run.cut)
    finally:
        env.close()
    if not success and not run.cut:
        raise RecordingError(f"seed {seed}: the operator did not complete the task ({extra})")
    extra |= {"scene": scene, "camera_axes": camera_axes, "operator_style": asdict(style)}
    extra |= {"set": {"task": plan.family.task, "seed": plan.set_seed, "slot": plan.slot}}
    if run.cut:
        extra["cut_at_step"] = max_steps
    meta, states = build_episode(
        run.trace,
        run.phases,
        phase_names,
        episode_id=plan.episode_id,
        task=families.task_info(plan),
        instruction=families.instruction(plan),
        target_bin=scenes.target_bin(plan.bin_index) if plan.bin_index is not None else None,
        seed=seed,
        success=success,
        extra=extra,
    )
    return Recorded(meta, run.trace.images, states, wall_s=time.perf_counter() - t0)


def record_slot(plan: SlotPlan, max_steps: int | None = None) -> Recorded:
    """The slot's episode from the first of its seeds the operator succeeds on; the failed ones, with their
    reasons, go into the episode (extra.skipped_seeds)."""
    skipped: list[dict] = []
    for seed in plan.seeds:
        try:
            rec = attempt(plan, seed, max_steps)
        except RecordingError as exc:
            skipped.append({"seed": seed, "reason": str(exc)})
            continue
        rec.skipped = skipped
        rec.meta["extra"]["skipped_seeds"] = skipped
        return rec
    reasons = "; ".join(f"{s['seed']}: {s['reason']}" for s in skipped)
    raise RecordingError(f"{plan.episode_id}: the operator failed on all {len(plan.seeds)} seeds ({reasons})")
