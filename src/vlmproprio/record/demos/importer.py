"""Importing demos: replay each, derive its ground truth, build and write its episode, update the manifest.

Episode ids are ``<prefix>_<nn>`` (``imp_<task>`` by default, ``nn`` the demo's
number: ``demo_7`` -> ``imp_door_07``). ``seed`` is -1 (not a seeded recording);
``extra`` names the source file and demo, the replay mode and the outcome.
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence
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
from vlmproprio.record import scenes
from vlmproprio.record.demos.env import ImportEnv, load_demo_model
from vlmproprio.record.demos.files import Demo, DemoFile, DemoImportError, read_demo, read_demo_file
from vlmproprio.record.demos.ground_truth import door_phases, pick_phases
from vlmproprio.record.demos.replay import REPLAY_MODES, Replay, replay
from vlmproprio.record.demos.tasks import task_for
from vlmproprio.record.recorder import Trace, build_episode

NO_SEED = -1


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


def _phases(trace: Trace, task: scenes.TaskInfo, target: int | None) -> tuple[list[str], Sequence[str]]:
    """(phase per step, the task's phase names) from the replay's simulator signals."""
    opening = np.array(trace.joints)[:, 7]
    if task.task == "door":
        return door_phases(opening, trace.signal("latch"), trace.signal("hinge")), scenes.DOOR_PHASES
    if task.task == "lift":
        names = scenes.LIFT_PHASES
        return pick_phases(opening, trace.signal("grip"), trace.signal("object"), names, transport=False), names
    names = scenes.bin_phases(target)
    return pick_phases(opening, trace.signal("grip"), trace.signal("object"), names, transport=True), names


def _extra(file: DemoFile, demo: Demo, rep: Replay, controller_note: str | None, axes, outcome: dict) -> dict:
    """The episode's ``extra``: where it came from, how it was replayed, and the outcome."""
    return {
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
    phases, phase_names = _phases(trace, task, target)
    extra = _extra(file, demo, rep, controller_note, axes, outcome)
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
