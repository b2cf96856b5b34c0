"""vlmproprio.parallel: chunks computed in forked processes come back whole, in order, errors as themselves."""

from __future__ import annotations

import os
import sys

import pytest

from vlmproprio.errors import UsageError
from vlmproprio.parallel import (
    WORKERS_ENV,
    ParallelError,
    chunk_bounds,
    deal_groups,
    default_workers,
    map_chunks,
    map_groups,
    parse_workers,
)

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="no fork on Windows: map_chunks runs one loop there")


@pytest.mark.parametrize("n", [0, 1, 2, 7, 24, 100])
@pytest.mark.parametrize("parts", [1, 2, 3, 8])
def test_chunk_bounds_cover_the_items_in_order_evenly(n, parts):
    bounds = chunk_bounds(n, parts)
    assert [i for a, b in bounds for i in range(a, b)] == list(range(n))
    sizes = [b - a for a, b in bounds]
    assert len(bounds) == max(1, min(parts, n)) and max(sizes) - min(sizes) <= 1


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


def _squares_with_pid(chunk):
    return [(x * x, os.getpid()) for x in chunk]


@pytest.mark.parametrize(("n", "workers", "min_chunk", "processes"), [(50, 3, 1, 3), (50, 3, 20, 2), (50, 3, 26, 1)])
def test_the_chunks_come_back_in_order_from_that_many_processes(n, workers, min_chunk, processes):
    parts = map_chunks(_squares_with_pid, list(range(n)), workers, min_chunk=min_chunk)
    flat = [x for part in parts for x in part]
    assert [sq for sq, _ in flat] == [i * i for i in range(n)]
    pids = [{pid for _, pid in part} for part in parts]
    assert all(len(p) == 1 for p in pids)  # each chunk in one process
    assert len(set().union(*pids)) == processes == len(parts)
    assert pids[0] == {os.getpid()}  # the first chunk in this process, the others in children


def _per_item(chunk):
    return [(x, x * x, os.getpid()) for x in chunk]


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
    assert map_chunks(lambda chunk: calls.append(list(chunk)) or len(chunk), range(10), 1) == [10]
    assert calls == [list(range(10))]


def test_a_workers_error_is_raised_as_itself_with_the_chunk_named():
    def fail_on_7(chunk):
        for x in chunk:
            if x == 7:
                raise UsageError(f"item {x} is bad")
        return list(chunk)

    with pytest.raises(UsageError, match=r"^item 7 is bad$") as info:
        map_chunks(fail_on_7, list(range(10)), 2)
    assert isinstance(info.value.__cause__, ParallelError)
    assert "items 6-10 of 10" in str(info.value.__cause__) and "fail_on_7" in str(info.value.__cause__)


def test_the_first_error_in_item_order_wins_as_in_one_loop():
    def fail_everywhere(chunk):
        raise ValueError(f"chunk starting at {chunk[0]}")

    with pytest.raises(ValueError, match="chunk starting at 0"):
        map_chunks(fail_everywhere, list(range(12)), 3)


def test_a_worker_that_dies_is_an_error_not_a_missing_part():
    def die_in_child(chunk):
        if chunk[0] != 0:
            os._exit(3)
        return list(chunk)

    with pytest.raises(ParallelError, match=r"items 6-10 of 10 died \(exit code 3\)"):
        map_chunks(die_in_child, list(range(10)), 2)


def test_a_result_that_cannot_be_sent_back_is_named():
    with pytest.raises(ParallelError, match=r"items 6-10 of 10 failed: its result cannot be sent back"):
        map_chunks(lambda chunk: lambda: chunk, list(range(10)), 2)


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
        map_chunks(fail, list(range(10)), 2)


def test_an_error_that_cannot_be_pickled_comes_back_as_its_traceback():
    def fail(chunk):
        if chunk[0]:
            exc = ValueError("unpicklable failure")
            exc.callback = lambda: None
            raise exc
        return list(chunk)

    with pytest.raises(ParallelError, match=r"(?s)items 6-10 of 10 failed: Traceback.*unpicklable failure"):
        map_chunks(fail, list(range(10)), 2)


def test_when_this_process_fails_the_workers_are_stopped_not_awaited():
    import time

    def slow_unless_first(chunk):
        if chunk[0] == 0:
            raise ValueError("first chunk")
        time.sleep(60)

    t = time.perf_counter()
    with pytest.raises(ValueError, match="first chunk"):
        map_chunks(slow_unless_first, list(range(10)), 2)
    assert time.perf_counter() - t < 30


def test_a_map_inside_a_worker_runs_in_that_worker():
    def inner(chunk):
        return {os.getpid()}

    def outer(chunk):
        return map_chunks(inner, list(chunk), 4)[0] | {os.getpid()}

    parts = map_chunks(outer, list(range(8)), 2)
    assert [len(p) for p in parts] == [1, 1]  # no grandchildren: each worker did its inner map itself


def test_text_written_before_the_fork_comes_out_once(tmp_path, monkeypatch):
    with open(tmp_path / "out.txt", "w", buffering=1 << 16) as out:  # block-buffered, as stdout into a pipe is
        monkeypatch.setattr(sys, "stdout", out)
        out.write("before the fork|")  # still in the buffer: a child must not flush a copy of it (multiprocessing
        # empties the std streams before it forks)
        map_chunks(_squares_with_pid, list(range(10)), 3)
        monkeypatch.undo()
    assert (tmp_path / "out.txt").read_text() == "before the fork|"


def test_inside_a_daemonic_process_the_map_is_one_loop_there():
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as pool:  # a pool's workers are daemonic: they may not start processes of their own
        pids = pool.apply(_pids_of_a_map)
    assert len(pids) == 1


def _pids_of_a_map() -> set[int]:
    return {pid for part in map_chunks(_squares_with_pid, list(range(10)), 3) for _, pid in part}


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
