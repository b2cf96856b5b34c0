"""Pure work split over forked processes: the same results, in the same order, as one loop over the items.

Scoring a whole run is CPU-bound Python (the rubric, segmentation sweeps), and so is replaying one with answers that
call no model (rules, a cassette); every cell and every episode is independent of the others. ``map_groups`` deals
whole groups of items (an episode's cells) out to chunks, computes the first chunk in this process and each other in
a child forked from it, and puts the per-item results back in the items' order. The children read the inputs from
the memory they inherit (nothing is pickled on the way in) and send back only their results, over multiprocessing's
own pipe. Because each result comes from the same function on the same items and results are put back in order, the
output is the one a single loop gives, bit for bit: no float is summed across chunks here.

Forking is only used where it is safe and pays: on platforms with ``fork``, outside daemonic processes and
other maps' workers, with more than one worker (``--workers``/``$VLMPROPRIO_WORKERS``, default: the cores
this process may use, at most 4, shared among pytest-xdist workers) and enough items per worker that a child
is worth its start. A child that fails raises its own error here (a UsageError stays one); one that dies is a
ParallelError naming its items, never a silently missing part.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import traceback
from collections.abc import Callable, Hashable, Sequence
from typing import TypeVar

from vlmproprio.errors import UsageError

T = TypeVar("T")
R = TypeVar("R")

WORKERS_ENV = "VLMPROPRIO_WORKERS"
MAX_DEFAULT_WORKERS = 4  # beyond this, scoring a 22-episode run is bound by its serial stages


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def parse_workers(value: str | int, where: str) -> int:
    """A worker count from a flag or the environment; a one-line error naming ``where`` when it is not one."""
    try:
        n = int(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: int(float("inf")) from a caller
        n = 0
    if n < 1:
        raise UsageError(f"{where} must be a whole number of worker processes, 1 or more (got {value!r})")
    return n


def default_workers() -> int:
    """``$VLMPROPRIO_WORKERS`` when set, else the cores this process may use (at most MAX_DEFAULT_WORKERS),
    shared with the other pytest-xdist workers when it is one of them."""
    env = os.environ.get(WORKERS_ENV)
    if env is not None and env.strip():
        return parse_workers(env.strip(), f"${WORKERS_ENV}")
    peers = os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")
    share = available_cores() // int(peers) if peers.isdigit() and int(peers) > 0 else available_cores()
    return max(1, min(share, MAX_DEFAULT_WORKERS))


def resolve_workers(workers: int | None) -> int:
    return default_workers() if workers is None else parse_workers(workers, "workers")


class ParallelError(RuntimeError):
    """A forked worker failed or died; the message names the chunk and carries the worker's traceback."""


# the job of the process being forked: a child reads it from the memory it inherits, not from a pickle
_JOB: tuple[Callable, Sequence] | None = None


def _child(conn, indices: Sequence[int]) -> None:
    fn, items = _JOB  # type: ignore[misc]
    try:
        try:
            result = fn(_pick(items, indices))
        except BaseException as exc:  # every failure goes back to the parent, which raises it
            # its traceback as text first: an error whose class cannot be rebuilt from its args still arrives
            conn.send(("error", traceback.format_exc()))
            try:
                conn.send(exc)
            except Exception:  # it cannot be pickled: the parent raises the traceback's text
                conn.send(None)
        else:
            try:
                conn.send(("ok", result))
            except Exception as exc:  # a result that cannot be pickled
                conn.send(("text", f"its result cannot be sent back ({type(exc).__name__}: {exc})"))
        conn.close()
    except OSError:  # the parent stopped listening (it failed first): nothing to report to
        pass
    # Leave now, without multiprocessing's exit path: it flushes stdout and stderr, whose locks another thread
    # of the parent (a progress bar's monitor, say) may have held when this process was forked.
    os._exit(0)


def _receive_error(receive) -> BaseException | None:
    """The worker's exception object, None when it could not be sent or rebuilt here."""
    try:
        error = receive.recv()
    except Exception:  # its class does not rebuild from its args: the traceback text stands in
        return None
    return error if isinstance(error, BaseException) else None


def _can_fork() -> bool:
    # not inside a map's worker (its children would multiply) nor in any daemonic process (a multiprocessing
    # pool's worker), which may not have children
    return (
        "fork" in multiprocessing.get_all_start_methods()
        and _JOB is None
        and not multiprocessing.current_process().daemon
    )


def _contiguous(indices: Sequence[int]) -> bool:
    """Whether ascending ``indices`` (never empty: deal_groups makes no empty chunk) are one run of items."""
    return indices[-1] - indices[0] == len(indices) - 1


def _pick(items: Sequence[T], indices: Sequence[int]) -> Sequence[T]:
    return items[indices[0] : indices[-1] + 1] if _contiguous(indices) else [items[i] for i in indices]


def _describe(indices: Sequence[int], total: int, what: str) -> str:
    if _contiguous(indices):
        return f"the worker for {what} {indices[0] + 1}-{indices[-1] + 1} of {total}"
    return f"the worker for {len(indices)} of {total} {what} (the first: number {indices[0] + 1})"


def _run(fn: Callable[[Sequence[T]], R], items: Sequence[T], chunks: list[list[int]], what: str) -> list[R]:
    """``fn`` of each chunk (a list of indices into ``items``, in order), the first here, the others in forked
    children; the results in chunk order. ``fn`` must be a pure function of its chunk (and of what it closes
    over, read-only): each child sees this process's memory as it was when forked, and what a child changes
    stays in the child."""
    global _JOB
    ctx = multiprocessing.get_context("fork")
    _JOB = (fn, items)
    children = []
    finished = False
    # The children read the parent's objects, which they share page by page until one is written to. The
    # cyclic collector writes to every object it visits: frozen, it visits none of those in the children.
    freeze = gc.get_freeze_count() == 0  # (if someone else froze objects, their freeze is left as it is)
    if freeze:
        gc.freeze()
    try:
        try:
            for indices in chunks[1:]:
                receive, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_child, args=(send, indices), daemon=True)
                proc.start()
                send.close()
                children.append((proc, receive, indices))
        finally:
            if freeze:
                gc.unfreeze()
        results = [fn(_pick(items, chunks[0]))]
        for proc, receive, indices in children:
            where = _describe(indices, len(items), what)
            try:
                message = receive.recv()  # before join: a large result would fill the pipe and stall the child
            except EOFError:
                proc.join()
                raise ParallelError(f"{where} died (exit code {proc.exitcode})") from None
            if message[0] == "error":  # the error a single loop would have raised, as it is (a UsageError stays one)
                error = _receive_error(receive)
                if error is None:
                    raise ParallelError(f"{where} failed: {message[1]}")
                raise error from ParallelError(f"{where}:\n{message[1]}")
            if message[0] == "text":
                raise ParallelError(f"{where} failed: {message[1]}")
            results.append(message[1])
        finished = True
        return results
    finally:
        _JOB = None
        for proc, receive, _ in children:
            receive.close()
            if not finished:  # this process failed first: the others' work is not wanted
                proc.kill()
            proc.join()


def deal_groups(keys: Sequence[Hashable], parts: int) -> list[list[int]]:
    """Indices of ``keys`` dealt into ``parts`` chunks, a whole group (equal keys) to one chunk, each group to
    the chunk with the fewest items so far (ties: the first), groups in order of first appearance; the indices
    of each chunk in ascending order. Alike items together keep what a worker remembers useful; dealing
    spreads the kinds of items over the workers, which keeps them about equally busy."""
    groups: dict[Hashable, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k, []).append(i)
    chunks: list[list[int]] = [[] for _ in range(max(1, parts))]
    for members in groups.values():
        min(chunks, key=len).extend(members)
    return [sorted(c) for c in chunks if c]


def map_groups(
    fn: Callable[[Sequence[T]], Sequence[R]],
    items: Sequence[T],
    workers: int,
    group: Callable[[T], Hashable],
    *,
    min_chunk: int = 1,
    what: str = "items",
) -> list[R]:
    """One result per item, in the items' order, from ``fn`` applied to chunks of whole groups of items
    (``deal_groups`` of ``group(item)``); ``fn`` returns one result per item of its chunk, in order. The same
    list as ``fn(items)`` for a pure ``fn`` (see ``_run``). With one worker, fewer than ``2 * min_chunk`` items,
    one group or no ``fork`` here: ``fn(items)``, in this process."""
    parts = min(workers, len(items) // max(1, min_chunk))
    if parts < 2 or not _can_fork():
        return list(fn(items))
    chunks = deal_groups([group(x) for x in items], parts)
    if len(chunks) < 2:
        return list(fn(items))
    out: list = [None] * len(items)
    for indices, results in zip(chunks, _run(fn, items, chunks, what), strict=True):
        if len(results) != len(indices):
            raise ParallelError(f"{what}: {len(results)} results for {len(indices)} items")
        for i, r in zip(indices, results, strict=True):
            out[i] = r
    return out
