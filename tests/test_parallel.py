"""vlmproprio.parallel: items computed in forked processes come back whole, in order, errors as themselves."""

from __future__ import annotations

import os
import sys

import pytest

from vlmproprio.errors import UsageError
from vlmproprio.parallel import (
    WORKERS_ENV,
    ParallelError,
    deal_groups,
    default_workers,
    map_groups,
    parse_workers,
)

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="no fork on Windows: map_groups runs one loop there")


@pytest.mark.parametrize("parts", [1, 2, 3, 5])
@pytest.mark.parametrize("seed", range(5))
def test_deal_groups_keeps_groups_whole_and_the_chunks_about_even(parts, seed):
    import random

    rng = random.Random(seed)
    keys = [rng.choice("abcdefgh") for _ in range(rng.randint(1, 60))]
    chunks = deal_groups(keys, parts)
    assert sorted(i for c in chunks for i in c) == list(range(len(keys)))
    assert all(c == sorted(c) for c in chunks) and len(chunks) <= parts
    owner = {keys[i]: n for n, c in enumerate(chunks) for i in c}
    assert all(owner[keys[i]] == n for n, c in enumerate(chunks) for i in c)  # a group in one chunk
    biggest = max(keys.count(k) for k in set(keys))
    assert max(map(len, chunks)) - min(map(len, chunks)) <= biggest


def _per_item(chunk):
    return [(x, x * x, os.getpid()) for x in chunk]


def _halves(x: int) -> bool:
    """Two groups of range(10): items 1-5 and 6-10, one chunk each."""
    return x >= 5


@pytest.mark.parametrize(("workers", "min_chunk", "processes"), [(3, 1, 3), (3, 20, 2), (3, 26, 1), (1, 1, 1)])
def test_the_items_come_back_in_order_from_that_many_processes(workers, min_chunk, processes):
    out = map_groups(_per_item, list(range(50)), workers, group=lambda x: x // 5, min_chunk=min_chunk)
    assert [(x, sq) for x, sq, _ in out] == [(i, i * i) for i in range(50)]
    pid_of: dict[int, int] = {}
    for x, _, pid in out:
        assert pid_of.setdefault(x // 5, pid) == pid  # a group in one process
    assert len(set(pid_of.values())) == processes
    assert pid_of[0] == os.getpid()  # the first chunk in this process, the others in children


def test_map_groups_gives_one_result_per_item_in_order_each_group_in_one_process():
    items = [7, 1, 7, 3, 1, 9, 3, 7, 2, 2, 9, 4] * 3
    out = map_groups(_per_item, items, 3, group=lambda x: x % 5)
    assert [(x, sq) for x, sq, _ in out] == [(x, x * x) for x in items]
    pid_of = {}
    for x, _, pid in out:
        assert pid_of.setdefault(x % 5, pid) == pid
    assert len(set(pid_of.values())) == 3


def test_map_groups_refuses_a_chunk_with_the_wrong_number_of_results():
    with pytest.raises(ParallelError, match="3 results for 4 items"):
        map_groups(lambda chunk: list(chunk)[:3] if chunk[0] else list(chunk), [0, 0, 0, 0, 1, 1, 1, 1], 2, group=bool)


def test_one_worker_is_one_call_here():
    calls = []
    assert map_groups(lambda chunk: calls.append(list(chunk)) or list(chunk), range(10), 1, group=_halves) == list(
        range(10)
    )
    assert calls == [list(range(10))]


def test_a_workers_error_is_raised_as_itself_with_the_chunk_named():
    def fail_on_7(chunk):
        for x in chunk:
            if x == 7:
                raise UsageError(f"item {x} is bad")
        return list(chunk)

    with pytest.raises(UsageError, match=r"^item 7 is bad$") as info:
        map_groups(fail_on_7, list(range(10)), 2, group=_halves)
    assert isinstance(info.value.__cause__, ParallelError)
    assert "items 6-10 of 10" in str(info.value.__cause__) and "fail_on_7" in str(info.value.__cause__)


def test_the_first_error_in_item_order_wins_as_in_one_loop():
    def fail_everywhere(chunk):
        raise ValueError(f"chunk starting at {chunk[0]}")

    with pytest.raises(ValueError, match="chunk starting at 0"):
        map_groups(fail_everywhere, list(range(12)), 3, group=lambda x: x // 4)


def test_a_worker_that_dies_is_an_error_not_a_missing_part():
    def die_in_child(chunk):
        if chunk[0] != 0:
            os._exit(3)
        return list(chunk)

    with pytest.raises(ParallelError, match=r"items 6-10 of 10 died \(exit code 3\)"):
        map_groups(die_in_child, list(range(10)), 2, group=_halves)
    with pytest.raises(ParallelError, match=r"the worker for 5 of 10 items \(the first: number 2\) died"):
        map_groups(die_in_child, list(range(10)), 2, group=lambda x: x % 2)  # the odd ones: not one run of items


def test_a_result_that_cannot_be_sent_back_is_named():
    with pytest.raises(ParallelError, match=r"items 6-10 of 10 failed: its result cannot be sent back"):
        map_groups(lambda chunk: lambda: chunk, list(range(10)), 2, group=_halves)


class _NeedsTwoArguments(Exception):
    def __init__(self, message, detail):
        super().__init__(message)
        self.detail = detail


def test_an_error_that_cannot_be_rebuilt_here_comes_back_as_its_traceback():
    def fail(chunk):
        if chunk[0]:
            raise _NeedsTwoArguments("odd failure", "x")
        return list(chunk)

    with pytest.raises(ParallelError, match=r"(?s)items 6-10 of 10 failed: Traceback.*odd failure"):
        map_groups(fail, list(range(10)), 2, group=_halves)


def test_this_projects_errors_come_back_with_their_attributes():
    from vlmproprio.cassettes import ReplayMissError
    from vlmproprio.chat import RequestTag

    tag = RequestTag("door_03", "both", "p1", 2)

    def fail(chunk):
        if chunk[0]:
            raise ReplayMissError("no recorded answer", "k" * 64, tag)
        return list(chunk)

    with pytest.raises(ReplayMissError, match=r"^no recorded answer$") as info:
        map_groups(fail, list(range(10)), 2, group=_halves)
    assert (info.value.key, info.value.tag) == ("k" * 64, tag) and isinstance(info.value.__cause__, ParallelError)


def test_an_error_that_cannot_be_pickled_comes_back_as_its_traceback():
    def fail(chunk):
        if chunk[0]:
            exc = ValueError("unpicklable failure")
            exc.callback = lambda: None
            raise exc
        return list(chunk)

    with pytest.raises(ParallelError, match=r"(?s)items 6-10 of 10 failed: Traceback.*unpicklable failure"):
        map_groups(fail, list(range(10)), 2, group=_halves)


def test_when_this_process_fails_the_workers_are_stopped_not_awaited(tmp_path):
    """Shown by the worker's own traces, not a clock: it started, never finished its minute of work, and its
    process is gone once map_groups has raised."""
    import time

    started, finished = tmp_path / "started", tmp_path / "finished"

    def slow_unless_first(chunk):
        if chunk[0] == 0:
            give_up = time.monotonic() + 120  # only ends a hang (a worker that never started): not a measurement
            while not started.exists():
                assert time.monotonic() < give_up, "the other chunk's worker never started"
                time.sleep(0.01)
            raise ValueError("first chunk")
        started.write_text(str(os.getpid()))
        time.sleep(60)
        finished.write_text("awaited")

    with pytest.raises(ValueError, match="first chunk"):
        map_groups(slow_unless_first, list(range(10)), 2, group=_halves)
    assert not finished.exists()  # awaited, the worker would have slept its minute and written this first
    with pytest.raises(ProcessLookupError):  # stopped and reaped
        os.kill(int(started.read_text()), 0)


def test_a_map_inside_a_worker_runs_in_that_worker():
    def inner(chunk):
        return [os.getpid()] * len(chunk)

    def outer(chunk):
        pids = frozenset(map_groups(inner, list(chunk), 4, group=lambda x: x)) | {os.getpid()}
        return [pids] * len(chunk)

    out = map_groups(outer, list(range(8)), 2, group=lambda x: x // 4)
    assert len(set(out)) == 2 and all(len(p) == 1 for p in out)  # no grandchildren: each did its inner map itself


def test_text_written_before_the_fork_comes_out_once(tmp_path, monkeypatch):
    with open(tmp_path / "out.txt", "w", buffering=1 << 16) as out:  # block-buffered, as stdout into a pipe is
        monkeypatch.setattr(sys, "stdout", out)
        out.write("before the fork|")  # still in the buffer: a child must not flush a copy of it (multiprocessing
        # empties the std streams before it forks)
        map_groups(_per_item, list(range(10)), 3, group=lambda x: x % 3)
        monkeypatch.undo()
    assert (tmp_path / "out.txt").read_text() == "before the fork|"


def test_inside_a_daemonic_process_the_map_is_one_loop_there():
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:  # a pool's workers are daemonic: they may not start processes of their own
        pids = pool.apply(_pids_of_a_map)
    assert len(pids) == 1


def _pids_of_a_map() -> set[int]:
    return {pid for _, _, pid in map_groups(_per_item, list(range(10)), 3, group=lambda x: x % 3)}


@pytest.mark.parametrize("value", ["0", "-1", "two", "1.5", ""])
def test_a_bad_worker_count_is_a_one_line_error_naming_where(value, monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, value)
    if not value.strip():
        assert default_workers() >= 1  # empty: unset
        return
    with pytest.raises(UsageError, match=rf"^\${WORKERS_ENV} must be a whole number"):
        default_workers()
    with pytest.raises(UsageError, match=r"^--workers must be"):
        parse_workers(value, "--workers")


def test_the_environment_sets_the_default(monkeypatch):
    monkeypatch.setenv(WORKERS_ENV, "3")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "8")
    assert default_workers() == 3


@pytest.mark.parametrize(
    ("cores", "xdist", "expected"), [(2, None, 2), (16, None, 4), (8, "2", 4), (2, "3", 1), (1, None, 1)]
)
def test_by_default_the_usable_cores_shared_with_other_xdist_workers(cores, xdist, expected, monkeypatch):
    monkeypatch.delenv(WORKERS_ENV, raising=False)
    monkeypatch.setattr("vlmproprio.parallel.available_cores", lambda: cores)
    if xdist is None:
        monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)
    else:
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", xdist)
    assert default_workers() == expected
