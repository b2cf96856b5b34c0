"""The task families new episodes are drawn from (``record/catalog.json``) and the plan of one episode set.

A set is (task, count, seed). Slot k of the set is the k-th episode: its target compartment is k mod 4
(pick-place), its object the (k div 4)-th of the task's objects, cycling, so both are balanced across the set.
Slot k first tries robosuite seed ``seed + k``; when the operator fails on a seed, the slot moves on by
``count`` (``seed + k + count``, then ``+ 2 * count``...), seeds no other slot of the set uses, so the
set always holds ``count`` episodes and no two slots share a scene.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from importlib import resources

from vlmproprio.errors import UsageError, VlmproprioError

CATALOG_FILE = "catalog.json"
# A slot whose operator fails on this many seeds in a row stops the recording: something is broken.
MAX_ATTEMPTS = 8


class CatalogError(VlmproprioError):
    """record/catalog.json is malformed."""


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a task family: the name episodes and captions use, and robosuite's name for it."""

    name: str
    robosuite: str | None
    grasp_above_m: float = 0.0
    onto: str | None = None


@dataclass(frozen=True)
class Family:
    """A task family of the catalog."""

    task: str  # also the lexicon the episodes are scored with (vlmproprio/lexicons/<task>.json)
    env: str
    camera: str
    operator: str
    action: str
    objects: tuple[ObjectSpec, ...]
    compartments: tuple[int, ...] = ()
    placement: tuple[tuple[str, tuple[float, float]], ...] = ()


@dataclass(frozen=True)
class SlotPlan:
    """What slot k of a set records: its id, object, compartment and the seeds it may try, in order."""

    episode_id: str
    family: Family
    slot: int
    set_seed: int
    obj: ObjectSpec
    bin_index: int | None
    seeds: tuple[int, ...]


def _family(task: str, spec: dict) -> Family:
    objects = tuple(
        ObjectSpec(name, o.get("robosuite"), float(o.get("grasp_above_m", 0.0)), o.get("onto"))
        for name, o in spec["objects"].items()
    )
    if not objects:
        raise ValueError(f"task {task!r} has no objects")
    placement = tuple((k, (float(v[0]), float(v[1]))) for k, v in spec.get("placement", {}).items())
    return Family(
        task=task,
        env=spec["env"],
        camera=spec["camera"],
        operator=spec["operator"],
        action=spec["action"],
        objects=objects,
        compartments=tuple(int(c) for c in spec.get("compartments", ())),
        placement=placement,
    )


@cache
def families() -> dict[str, Family]:
    """The catalog's task families by task name."""
    raw = resources.files("vlmproprio").joinpath("record", CATALOG_FILE).read_text()
    try:
        data = json.loads(raw)
        return {task: _family(task, spec) for task, spec in data["tasks"].items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise CatalogError(f"vlmproprio/record/{CATALOG_FILE}: malformed ({exc!r})") from exc


def family(task: str) -> Family:
    known = families()
    if task not in known:
        raise UsageError(f"unknown task {task!r} for record --task (known: {', '.join(known)})")
    return known[task]


def slot_plan(task: str, count: int, seed: int, slot: int) -> SlotPlan:
    fam = family(task)
    obj = fam.objects[(slot // 4) % len(fam.objects)] if fam.compartments else fam.objects[slot % len(fam.objects)]
    bin_index = fam.compartments[slot % len(fam.compartments)] if fam.compartments else None
    seeds = tuple(seed + slot + a * count for a in range(MAX_ATTEMPTS))
    return SlotPlan(f"{task}-s{seed}-{slot:03d}", fam, slot, seed, obj, bin_index, seeds)


def set_plan(task: str, count: int, seed: int) -> list[SlotPlan]:
    """Every slot of the set (task, count, seed)."""
    if count < 1:
        raise UsageError(f"record --count must be at least 1, got {count}")
    if seed < 0:
        raise UsageError(f"record --seed must be at least 0, got {seed}")
    return [slot_plan(task, count, seed, k) for k in range(count)]
