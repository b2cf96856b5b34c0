"""Record a new episode set (``vlmproprio record --task stack --count 8 --seed 0 --out DIR``), in parallel and
resumable.

Each slot is recorded in a process of its own (``--workers``), into ``DIR/.partial/<id>.<pid>/`` and renamed
into ``DIR/episodes/<id>`` once whole: an episode folder is there complete or not at all. A killed recording
leaves at most partial folders, which the next run deletes before recording the slots still missing. Every
slot draws its scene and operator from its own seeds (``catalog.slot_plan``), so the set is the same
whichever worker records which slot, and however often it was interrupted. ``DIR/recording.json`` names the
set; the manifest is rewritten when every slot is there.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.episodes import write_episode, write_manifest
from vlmproprio.errors import UsageError
from vlmproprio.io import atomic_write_text, load_json
from vlmproprio.record.catalog import SlotPlan, set_plan

PARTIAL_DIR = ".partial"
SET_FILE = "recording.json"


@dataclass(frozen=True)
class SlotDone:
    episode_id: str
    seed: int
    steps: int
    frames: int
    wall_s: float
    skipped: tuple[tuple[int, str], ...]


def record_into(plan: SlotPlan, out: Path, max_steps: int | None = None) -> SlotDone:
    """Record one slot and move it into ``out/episodes/`` in one rename (run in a worker process)."""
    from vlmproprio.record.generate import record_slot

    rec = record_slot(plan, max_steps)
    tmp_root = out / PARTIAL_DIR / f"{plan.episode_id}.{os.getpid()}"
    if tmp_root.exists():
        shutil.rmtree(tmp_root)
    folder = write_episode(tmp_root, rec.meta, rec.images, rec.states)
    final = out / "episodes" / plan.episode_id
    if final.exists():  # a folder without its episode.json: not whole, so not kept
        shutil.rmtree(final)
    os.replace(folder, final)
    shutil.rmtree(tmp_root, ignore_errors=True)
    skipped = tuple((s["seed"], s["reason"]) for s in rec.skipped)
    return SlotDone(plan.episode_id, rec.meta["seed"], rec.meta["steps"], len(rec.images), rec.wall_s, skipped)


def set_doc(task: str, count: int, seed: int, max_steps: int | None) -> dict:
    """What ``DIR/recording.json`` says of a set (task, count, seed), and the versions that recorded it."""
    return with_versions({"task": task, "count": count, "seed": seed}, max_steps)


def with_versions(doc: dict, max_steps: int | None) -> dict:
    from vlmproprio.record.recorder import versions

    doc = {**doc, "versions": versions()}
    if max_steps is not None:
        doc["max_steps"] = max_steps
    return doc


def _prepare(out: Path, doc: dict) -> None:
    """Create ``out``, or check that it holds this set (a resumed recording); drop partial episodes."""
    (out / "episodes").mkdir(parents=True, exist_ok=True)
    path = out / SET_FILE
    if path.is_file():
        old = load_json(path, error=UsageError)
        old = old if isinstance(old, dict) else {}
        if old != doc:  # another task, count, seed, --max-steps or robosuite/MuJoCo version
            raise UsageError(
                f"{out} holds another episode set ({path}: {json.dumps(old, sort_keys=True)}); record into "
                "another --out, or run with the same --set, or --task, --count and --seed, to resume it"
            )
    else:
        atomic_write_text(path, json.dumps(doc, indent=1, sort_keys=True) + "\n")
    shutil.rmtree(out / PARTIAL_DIR, ignore_errors=True)


def missing_slots(out: Path, plans: list[SlotPlan]) -> list[SlotPlan]:
    """The slots with no whole episode in ``out`` (an episode folder is whole once it is there)."""
    return [p for p in plans if not (out / "episodes" / p.episode_id / "episode.json").is_file()]


def _run_serial(todo, out, max_steps, bar, results) -> None:
    for plan in todo:
        results.append(record_into(plan, out, max_steps))
        _advance(bar, results[-1])


def _run_parallel(todo, out, max_steps, workers, bar, results) -> None:
    # spawn, not fork: each worker starts its own MuJoCo and OpenGL context instead of copying this one's
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        pending = {pool.submit(record_into, plan, out, max_steps) for plan in todo}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    results.append(fut.result())
                    _advance(bar, results[-1])
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise


def _advance(bar, done: SlotDone) -> None:
    bar.update(1)
    bar.set_postfix_str(
        f"{done.episode_id} seed {done.seed}" + (f", {len(done.skipped)} seeds skipped" * bool(done.skipped))
    )


def record_set(
    task: str,
    count: int,
    seed: int,
    out: Path,
    *,
    workers: int = 1,
    max_steps: int | None = None,
    progress: bool = True,
) -> list[SlotDone]:
    """Record the slots of (task, count, seed) missing from ``out``, rewrite its manifest, return what was
    recorded now. ``max_steps`` cuts every episode short, unjudged (tests and timing)."""
    plans = set_plan(task, count, seed)
    doc = set_doc(task, count, seed, max_steps)
    return record_plans(plans, Path(out), doc, workers=workers, max_steps=max_steps, progress=progress, desc=task)


def record_plans(
    plans: list[SlotPlan],
    out: Path,
    doc: dict,
    *,
    workers: int = 1,
    max_steps: int | None = None,
    progress: bool = True,
    desc: str = "",
) -> list[SlotDone]:
    """Record the slots of ``plans`` missing from ``out`` (a folder whose recording.json is ``doc``, or a new
    one), rewrite its manifest, return what was recorded now, sorted by episode id."""
    from tqdm import tqdm

    _prepare(out, doc)
    todo = missing_slots(out, plans)
    results: list[SlotDone] = []
    t0 = time.perf_counter()
    with tqdm(
        total=len(plans), initial=len(plans) - len(todo), desc=f"recording {desc}", unit="episode", disable=not progress
    ) as bar:
        if workers <= 1 or len(todo) <= 1:
            _run_serial(todo, out, max_steps, bar, results)
        else:
            _run_parallel(todo, out, max_steps, min(workers, len(todo)), bar, results)
    shutil.rmtree(out / PARTIAL_DIR, ignore_errors=True)
    write_manifest(out)
    _print_summary(results, len(plans) - len(todo), time.perf_counter() - t0)
    return sorted(results, key=lambda r: r.episode_id)


def _print_summary(results: list[SlotDone], kept: int, wall: float) -> None:
    for r in sorted(results, key=lambda r: r.episode_id):
        for seed, reason in r.skipped:
            print(f"{r.episode_id}: skipped seed {seed}: {reason}")
    steps = [r.steps for r in results]
    line = f"recorded {len(results)} episodes in {wall:.1f} s"
    if steps:
        line += f" ({min(steps)}-{max(steps)} steps)"
    if kept:
        line += f"; {kept} already there were kept"
    print(line)
