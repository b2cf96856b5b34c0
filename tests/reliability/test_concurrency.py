"""Item 2, concurrency: four processes run overlapping episodes against one response cache.

Each worker is a real ``vlmproprio.runner.run`` (the code behind ``vlmproprio run``) in its own process
(multiprocessing, forked from a server that imported vlmproprio once: fast_support), started together behind
a barrier, live mode, the reference model (instant, so the processes hammer the SQLite cache as hard as they
can). Every answer must be stored exactly once (the stored
counts of the four runs add up to the number of entries), none lost (the cache equals that of one process
running every episode alone), every worker's transcripts equal the solo run's, and no worker fails (no
"database is locked").

The cache-level version of this (four processes, synthetic requests, a slow fake model) is
tests/test_cache.py::test_four_processes_share_one_cache.
"""

from __future__ import annotations

import traceback
from pathlib import Path

from fast_support import fork_context
from reliability_support import cache_answers, fixture_subset, transcripts_of

EPISODES = ["door_00", "door_05", "bin0_01", "bin1_02", "bin2_00", "bin3_01"]
WORKERS = 4
ROUNDS = 2


def _windows(round_: int) -> list[list[str]]:
    """Worker i runs three consecutive episodes starting at i (+ round), odd workers in reverse order."""
    out = []
    for i in range(WORKERS):
        window = [EPISODES[(i + round_ + j) % len(EPISODES)] for j in range(3)]
        out.append(window[::-1] if i % 2 else window)
    return out


def _plan(fixtures: Path, out: Path, cache: Path, episodes: list[str]):
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.runner import RunPlan

    return RunPlan(
        models=("reference",),
        conditions=tuple(parse_conditions("all")),
        fixtures=fixtures,
        out=out,
        episode_ids=tuple(episodes),
        mode="live",
        cache_dir=cache,
        progress=False,
    )


def _worker(fixtures: str, out: str, cache: str, episodes: list[str], barrier, results) -> None:
    from vlmproprio.runner import run

    try:
        plan = _plan(Path(fixtures), Path(out), Path(cache), episodes)
        barrier.wait(timeout=120)  # start together
        (model_run,) = run(plan)
        results.put({"out": out, "stats": model_run.stats, "error": None})
    except BaseException as exc:  # report everything, "database is locked" included
        results.put({"out": out, "stats": None, "error": f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"})


def test_four_processes_overlapping_episodes_one_cache(tmp_path, figures):
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.runner import run

    fixtures = fixture_subset(tmp_path / "fixtures", EPISODES)
    solo_cache = tmp_path / "solo-cache"
    (solo,) = run(_plan(fixtures, tmp_path / "solo", solo_cache, EPISODES))
    expected_answers = cache_answers(solo_cache)
    expected_transcripts = transcripts_of(tmp_path / "solo")
    n_conditions = len(parse_conditions("all"))  # the paper's four and every control
    assert len(expected_answers) == solo.stats["stored"] > 500
    assert len(expected_transcripts) == len(EPISODES) * n_conditions

    # no fork of this process: it holds open databases and threads; each worker is forked from a server that
    # holds neither and imported vlmproprio once (fast_support), instead of a spawned interpreter importing it
    ctx = fork_context()
    requests_total = stored_total = errors = 0
    for round_ in range(ROUNDS):
        shared = tmp_path / f"shared-cache-{round_}"
        barrier, results = ctx.Barrier(WORKERS), ctx.Queue()
        windows = _windows(round_)
        procs = [
            ctx.Process(
                target=_worker,
                args=(str(fixtures), str(tmp_path / f"r{round_}-w{i}"), str(shared), windows[i], barrier, results),
            )
            for i in range(WORKERS)
        ]
        for p in procs:
            p.start()
        got = [results.get(timeout=300) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        failures = [g["error"] for g in got if g["error"]]
        errors += len(failures)
        assert failures == [], "\n".join(failures)  # no "database is locked", no crash
        assert [p.exitcode for p in procs] == [0] * WORKERS

        answers = cache_answers(shared)  # checksums verified, no key twice
        stored = sum(g["stats"]["stored"] for g in got)
        assert stored == len(answers)  # each answer stored by exactly one process
        assert answers == expected_answers  # none lost, none different
        assert sum(g["stats"]["stored"] > 0 for g in got) >= 2  # they really worked side by side
        for g in got:
            ts = transcripts_of(Path(g["out"]))
            assert ts and ts.items() <= expected_transcripts.items()
        requests_total += sum(g["stats"]["hits"] + g["stats"]["misses"] for g in got)
        stored_total += stored

    figures(
        "concurrency",
        rounds=ROUNDS,
        processes_per_round=WORKERS,
        requests_answered=requests_total,
        answers_stored=stored_total,
        stored_twice=0,
        entries_lost=0,
        database_locked_errors=errors,
    )
