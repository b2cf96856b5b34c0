"""New episode sets (`vlmproprio record --task T --count N --seed S --out DIR`): the plan balances compartments
and objects, a set is bit-identical however it was recorded (serially, by two workers, killed and resumed), a
seed the operator fails on gives way to the slot's next one, and no half-written episode is ever kept.

Episodes here are cut after a few steps (``max_steps``): what is tested is the recording machinery, not the
operators (whose whole runs tests/record/test_recorder.py and the perf script exercise)."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from vlmproprio.errors import UsageError
from vlmproprio.record.catalog import families, set_plan

needs_robosuite = pytest.mark.skipif(
    importlib.util.find_spec("robosuite") is None,
    reason="recording needs the [record] extra (robosuite==1.5.2, mujoco==3.3.7): pip install -e .[record]",
)
TASK, COUNT, SEED, STEPS = "pick_place", 3, 7, 25  # 2 frames per episode


def test_a_pick_place_set_balances_compartments_and_objects():
    plans = set_plan("pick_place", 32, 0)
    assert Counter(p.bin_index for p in plans) == {0: 8, 1: 8, 2: 8, 3: 8}
    assert Counter(p.obj.robosuite for p in plans) == {"cereal": 8, "milk": 8, "bread": 8, "can": 8}
    assert len({(p.obj.name, p.bin_index) for p in plans[:16]}) == 16  # every object in every compartment
    assert len({p.episode_id for p in plans}) == 32


def test_slots_never_share_a_seed_and_start_from_the_set_seed():
    plans = set_plan("door", 5, 40)
    assert [p.seeds[0] for p in plans] == [40, 41, 42, 43, 44]
    all_seeds = [s for p in plans for s in p.seeds]
    assert len(all_seeds) == len(set(all_seeds))
    assert plans[2].seeds[1] == 47  # a failed seed gives way to seed + count


def test_every_catalog_task_has_a_lexicon_and_the_plan_refuses_nonsense():
    from vlmproprio.scoring.lexicon import available_tasks

    assert set(families()) <= set(available_tasks())
    with pytest.raises(UsageError, match="unknown task"):
        set_plan("juggle", 2, 0)
    with pytest.raises(UsageError, match="at least 1"):
        set_plan("door", 0, 0)


def test_record_task_needs_count_and_out(capsys):
    from vlmproprio.cli import main

    assert main(["record", "--task", "door", "--count", "2"]) != 0
    assert "--out" in capsys.readouterr().err
    assert main(["record", "--count", "2", "--out", "x"]) != 0
    assert "--task" in capsys.readouterr().err


def _files(root: Path) -> dict[str, str]:
    return json.loads((root / "manifest.json").read_text())["files"]


@pytest.fixture(scope="module")
def parallel_set(tmp_path_factory) -> Path:
    """The set recorded by two worker processes."""
    from vlmproprio.record.sets import record_set

    out = tmp_path_factory.mktemp("parallel") / "set"
    record_set(TASK, COUNT, SEED, out, workers=2, max_steps=STEPS, progress=False)
    return out


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "vlmproprio.cli", "record", *args]


@needs_robosuite
@pytest.mark.record
@pytest.mark.slow
def test_a_killed_recording_resumes_to_the_same_bits_as_one_by_two_workers(tmp_path: Path, parallel_set: Path):
    from vlmproprio.episodes import load_episodes
    from vlmproprio.record.sets import PARTIAL_DIR, record_set

    out = tmp_path / "set"
    args = ["--task", TASK, "--count", str(COUNT), "--seed", str(SEED), "--out", str(out)]
    proc = subprocess.Popen(_cli(*args, "--max-steps", str(STEPS), "--no-progress"), stdout=subprocess.DEVNULL)
    first = out / "episodes" / f"{TASK}-s{SEED}-000" / "episode.json"
    deadline = time.monotonic() + 120
    while not first.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert first.is_file() and not (out / "manifest.json").exists()  # killed in the middle
    # what a kill in the middle of writing leaves: a partial folder, and an episode folder without its json
    (out / PARTIAL_DIR / "x.1" / "episodes").mkdir(parents=True)
    half = out / "episodes" / f"{TASK}-s{SEED}-002"
    (half / "frames").mkdir(parents=True, exist_ok=True)

    resumed = record_set(TASK, COUNT, SEED, out, workers=1, max_steps=STEPS, progress=False)
    assert 1 <= len(resumed) <= COUNT - 1  # the first episode was kept
    assert not (out / PARTIAL_DIR).exists()
    assert _files(out) == _files(parallel_set)  # every file, frames included, bit for bit
    assert [e.episode_id for e in load_episodes(out)] == [f"{TASK}-s{SEED}-{k:03d}" for k in range(COUNT)]
    assert record_set(TASK, COUNT, SEED, out, max_steps=STEPS, progress=False) == []  # nothing left to do


@needs_robosuite
@pytest.mark.record
def test_a_set_records_varied_scenes_with_ground_truth(parallel_set: Path):
    from vlmproprio.episodes import load_episodes

    eps = load_episodes(parallel_set)
    assert [e.target_bin.index for e in eps] == [0, 1, 2]
    assert [e.seed for e in eps] == [SEED, SEED + 1, SEED + 2]
    starts = {tuple(e.extra["scene"]["object_start"]) for e in eps}
    assert len(starts) == COUNT  # robosuite's placement sampler, seeded per episode
    for e in eps:
        assert e.env_name == "PickPlaceCereal" and e.target_object == "cereal box"
        assert e.extra["skipped_seeds"] == [] and e.extra["cut_at_step"] == STEPS
        assert {f.phase for f in e.frames} <= set(e.phase_names) and e.frames[0].direction
    with pytest.raises(UsageError, match="another episode set"):
        from vlmproprio.record.sets import record_set

        record_set(TASK, COUNT + 1, SEED, parallel_set, max_steps=STEPS, progress=False)


@needs_robosuite
@pytest.mark.record
def test_a_failing_seed_is_skipped_with_its_reason_and_the_count_holds(tmp_path: Path, monkeypatch, capsys):
    from vlmproprio.record import generate
    from vlmproprio.record.recorder import RecordingError
    from vlmproprio.record.sets import record_set

    real = generate.attempt

    def flaky(plan, seed, max_steps=None):
        if seed == 3:
            raise RecordingError(f"seed {seed}: the operator did not complete the task (dropped it)")
        return real(plan, seed, max_steps)

    monkeypatch.setattr(generate, "attempt", flaky)
    done = record_set("stack", 2, 3, tmp_path, max_steps=STEPS, progress=False)
    assert [d.seed for d in done] == [5, 4]  # slot 0 moved on from seed 3 to 3 + count
    meta = json.loads((tmp_path / "episodes" / "stack-s3-000" / "episode.json").read_text())
    assert meta["seed"] == 5 and meta["task"] == "stack"
    assert meta["extra"]["skipped_seeds"] == [
        {"seed": 3, "reason": "seed 3: the operator did not complete the task (dropped it)"}
    ]
    assert "stack-s3-000: skipped seed 3" in capsys.readouterr().out


@needs_robosuite
@pytest.mark.record
@pytest.mark.slow
def test_a_stack_episode_is_scored_with_directions_from_its_own_trajectory(tmp_path: Path):
    """A whole Stack episode: the operator succeeds, and the rubric's expected carry directions are the hand's
    displacement in its transport phase, in the words of the episode's own camera."""
    from vlmproprio.episodes import load_episode
    from vlmproprio.record.sets import record_set
    from vlmproprio.scoring.expectation import expectation_for
    from vlmproprio.scoring.rubric import score_caption

    record_set("stack", 1, 2, tmp_path, progress=False)
    ep = load_episode(tmp_path, "stack-s2-000")
    assert ep.success and ep.env_name == "Stack" and ep.extra["skipped_seeds"] == []
    lift, carry = expectation_for(ep).motions
    assert lift.expected == ("up",)
    a, b = ep.extra["scene"]["object_start"], ep.extra["under_object_pos"]
    forward = "forward" if b[0] > a[0] else "backward"
    assert forward in carry.expected or abs(b[0] - a[0]) < 0.35 * abs(b[1] - a[1])
    words = " and ".join(d.replace("robot_", "to the robot's ") for d in carry.expected[:1])
    good = score_caption(f"The robot picks up the red cube, moves it {words} and stacks it on the green cube.", ep)
    assert good.object.correct and good.action.correct and good.trajectory.correct
    bad = score_caption(f"The robot picks up the red cube, moves it {carry.opposite[0]} and stacks it.", ep)
    assert bad.trajectory.wrong
