"""Item 1, kill and resume: a live run killed with SIGKILL at seeded random points, then resumed, ends exactly
where an uninterrupted run ends.

The run is the real CLI (`vlmproprio run`) in a process of its own (forked from a server that imported the CLI
once, fast_support.CliProcess: the imports are not what is killed), answering through the openai backend from the
loopback server in this process (answers depend only on the request, so every run gets the same ones, and
the server counts requests, which places kills inside the run rather than only at its start). After each
kill: every cache entry passes its checksum and holds the uninterrupted run's answer, every transcript file
on disk parses and equals the uninterrupted one, run.json parses. After the resume: the same answers and
transcripts as the uninterrupted run, and the resumed run asked the server only for what the cache lacked.

The openai backend stores a batch of answers when the batch is done, so most of those kills fall between
cache writes; a second test kills the reference model's run (instant answers, one SQLite transaction each)
at a seeded number of committed entries, so the kills land inside the stream of cache writes.
"""

from __future__ import annotations

import random
import sqlite3
import time
from pathlib import Path

import pytest
from fast_support import CliProcess, forked_cli
from reliability_support import (
    cache_answers,
    caption_responder,
    fixture_subset,
    run_file,
    temp_leftovers,
    transcripts_of,
)

from extras import needs_openai
from vlmproprio.testing.openai_server import FakeOpenAIServer

# checked, not imported: collecting this module on every xdist worker must not cost the SDK's ~1 CPU s
pytestmark = needs_openai

KILLS = 24
KILLS_PER_CHAIN = 3
SEED = 8_2026
EPISODES = ["door_00"]
CONDITIONS = "none,both,primitives"


def _run_args(server: FakeOpenAIServer, fixtures: Path, out: Path, cache: Path) -> list[str]:
    return [
        "run",
        "--model",
        "openai:fake-vlm",
        "--base-url",
        server.base_url,
        "--fixtures",
        fixtures,
        "--episodes",
        *EPISODES,
        "--conditions",
        CONDITIONS,
        "--frame-stride",
        "2",
        "--concurrency",
        "2",
        "--timeout",
        "20",
        "--no-progress",
        "--out",
        out,
        "--cache-dir",
        cache,
    ]


def _kill_at(proc: CliProcess, server: FakeOpenAIServer, seen_before: int, n_requests: int, delay: float):
    """SIGKILL ``proc`` ``delay`` seconds after the server has received ``n_requests`` of its requests."""
    deadline = time.monotonic() + 60
    while len(server.chat_requests) - seen_before < n_requests and proc.poll() is None:
        assert time.monotonic() < deadline, "the run stopped making requests"
        time.sleep(0.002)
    time.sleep(delay)
    if proc.poll() is None:
        proc.kill()  # SIGKILL: no handler, no cleanup, no flush
    proc.wait(timeout=30)


@pytest.mark.slow
def test_sigkill_at_random_points_then_resume_gives_the_uninterrupted_run(tmp_path, figures):
    fixtures = fixture_subset(tmp_path / "fixtures", EPISODES)
    with FakeOpenAIServer(latency_s=0.01, responder=caption_responder) as server:
        t0 = time.monotonic()
        straight = forked_cli(
            _run_args(server, fixtures, tmp_path / "straight", tmp_path / "straight-cache"), tmp_path / "logs"
        )
        straight_s = time.monotonic() - t0
        assert straight.returncode == 0, straight.stderr
        n_requests = len(server.chat_requests)
        expected_answers = cache_answers(tmp_path / "straight-cache")
        expected_transcripts = transcripts_of(tmp_path / "straight")
        assert len(expected_answers) == n_requests == 3 * 9  # 16 frames at stride 2, k=5: 2*4+1 calls each
        assert len(expected_transcripts) == 3

        rng = random.Random(SEED)
        kills = finished_first = kept = leftovers = 0
        phases = {"before_storing_anything": 0, "while_answering": 0, "after_last_answer": 0}
        chain = 0
        while kills < KILLS:
            assert chain < 3 * KILLS // KILLS_PER_CHAIN, f"only {kills} SIGKILLs landed inside a run"
            # one run directory and cache, killed up to KILLS_PER_CHAIN times in a row (a resumed run can die
            # too), then resumed to the end
            out, cache = tmp_path / f"c{chain}", tmp_path / f"c{chain}-cache"
            chain += 1
            for _ in range(min(KILLS_PER_CHAIN, KILLS - kills)):
                stored = len(cache_answers(cache))
                to_ask = n_requests - stored
                # a point anywhere in the run: during start-up, after its n-th request reached the server, or
                # after its last one (while transcripts and run.json are written)
                n = rng.randint(0, to_ask + 1)
                if n == 0:
                    delay = rng.uniform(0, 0.8)
                elif n <= to_ask:
                    delay = rng.uniform(0, 0.05)
                else:
                    n, delay = to_ask, rng.uniform(0, 0.15)
                seen = len(server.chat_requests)
                proc = CliProcess(_run_args(server, fixtures, out, cache), tmp_path / "logs")
                _kill_at(proc, server, seen, n, delay)
                err = proc.stderr()
                if proc.returncode == 0:
                    finished_first += 1  # the run won the race: not a kill, not counted
                    break
                assert proc.returncode == -9, err
                kills += 1

                # the interrupted state: nothing half-written, nothing that differs from the straight run
                answers = cache_answers(cache)
                assert answers.items() <= expected_answers.items()
                assert transcripts_of(out).items() <= expected_transcripts.items()
                doc = run_file(out)  # parses, or is absent: never half a file
                assert doc is None or doc["status"] in ("running", "complete")
                leftovers += len(temp_leftovers(out))
                if len(answers) == stored and stored < n_requests:
                    phases["before_storing_anything"] += 1
                elif len(answers) < n_requests:
                    phases["while_answering"] += 1
                else:
                    phases["after_last_answer"] += 1

            answers = cache_answers(cache)
            seen = len(server.chat_requests)
            resumed = forked_cli(_run_args(server, fixtures, out, cache), tmp_path / "logs")
            assert resumed.returncode == 0, resumed.stderr
            # nothing already stored is asked again, nothing missing is skipped
            assert len(server.chat_requests) - seen == n_requests - len(answers)
            kept += len(answers)
            assert cache_answers(cache) == expected_answers  # none lost, none changed, none stored twice
            assert transcripts_of(out) == expected_transcripts
            assert run_file(out)["status"] == "complete"

    assert phases["while_answering"] >= 3  # some kills fell between the run's first and last stored answer
    figures(
        "kill and resume",
        sigkills=kills,
        chains=chain,
        finished_before_kill=finished_first,
        killed_before_storing_anything=phases["before_storing_anything"],
        killed_while_answering=phases["while_answering"],
        killed_after_last_answer=phases["after_last_answer"],
        answers_kept_across_kills=kept,
        requests_per_run=n_requests,
        straight_run_s=round(straight_s, 2),
        temp_files_left_by_kills=leftovers,
        entries_lost=0,
        half_written_files=0,
    )


REF_EPISODES = ["door_00", "bin1_00"]
REF_KILLS = 12


def _kill_when_stored(proc: CliProcess, db: Path, n_entries: int, delay: float) -> None:
    """SIGKILL ``proc`` ``delay`` seconds after the cache database holds ``n_entries`` committed entries."""
    deadline = time.monotonic() + 60
    conn = None
    try:
        while proc.poll() is None:
            assert time.monotonic() < deadline, "the run stopped storing answers"
            if conn is None and db.exists():
                conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
            try:
                if conn is not None and conn.execute("SELECT COUNT(*) FROM Cache").fetchone()[0] >= n_entries:
                    break
            except sqlite3.OperationalError:  # the table is being created
                pass
            time.sleep(0.0005)
    finally:
        if conn is not None:
            conn.close()
    time.sleep(delay)
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=30)


@pytest.mark.slow
def test_sigkill_while_answers_are_being_stored(tmp_path, figures):
    """The reference model answers instantly and each answer is its own SQLite transaction: kills placed by
    the number of entries already committed land inside the stream of cache writes."""
    fixtures = fixture_subset(tmp_path / "fixtures", REF_EPISODES)

    def args(out: Path, cache: Path) -> list[str]:
        head = ["run", "--model", "reference", "--fixtures", str(fixtures), "--conditions", "none,both,primitives"]
        return [*head, "--no-progress", "--out", str(out), "--cache-dir", str(cache)]

    straight = forked_cli(args(tmp_path / "straight", tmp_path / "straight-cache"), tmp_path / "logs")
    assert straight.returncode == 0, straight.stderr
    expected_answers = cache_answers(tmp_path / "straight-cache")
    expected_transcripts = transcripts_of(tmp_path / "straight")
    rng = random.Random(SEED + 1)
    kills = mid_stream = trial = 0
    while kills < REF_KILLS:
        assert trial < 3 * REF_KILLS, f"only {kills} SIGKILLs landed inside a run"
        out, cache = tmp_path / f"r{trial:02d}", tmp_path / f"r{trial:02d}-cache"
        trial += 1
        n = rng.randint(1, len(expected_answers) - 1)
        proc = CliProcess(args(out, cache), tmp_path / "logs")
        _kill_when_stored(proc, cache / "cache.db", n, rng.uniform(0, 0.003))
        if proc.returncode == 0:
            continue
        assert proc.returncode == -9
        kills += 1
        answers = cache_answers(cache)  # every committed entry whole and checksummed
        assert answers.items() <= expected_answers.items()
        assert transcripts_of(out).items() <= expected_transcripts.items()
        mid_stream += 0 < len(answers) < len(expected_answers)
        resumed = forked_cli(args(out, cache), tmp_path / "logs")
        assert resumed.returncode == 0, resumed.stderr
        assert cache_answers(cache) == expected_answers
        assert transcripts_of(out) == expected_transcripts
    assert mid_stream >= kills // 2
    figures(
        "kill while storing",
        sigkills=kills,
        runs_that_finished_first=trial - kills,
        killed_between_first_and_last_entry=mid_stream,
        entries_per_run=len(expected_answers),
        entries_lost=0,
        half_written_entries=0,
    )
