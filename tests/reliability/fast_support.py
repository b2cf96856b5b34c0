"""The real CLI in a real process, without paying Python's start-up in every one of them.

Kill tests start dozens of `vlmproprio run` processes and SIGKILL them: the separate process is the point,
but each ``python -m vlmproprio.cli`` spends most of its CPU importing (the openai SDK alone is ~1 s), which
says nothing about kills. ``cli_process`` forks each run from a multiprocessing fork server that imported
those modules once (imports only: no file, database or thread is open when it forks), so every run is still
its own process, with its own PID, killed by the kernel, its exit status -9, running the same
``vlmproprio.cli.main`` that ``python -m vlmproprio.cli`` runs, and exiting through the same interpreter
shut-down (non-daemon threads joined, streams flushed).
"""

from __future__ import annotations

import atexit
import multiprocessing
import multiprocessing.forkserver
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from reliability_support import REPO, cli_env

# What `vlmproprio run` imports (reference and openai backends): imported once, in the fork server.
PRELOAD = (
    "vlmproprio.cli",
    "vlmproprio.runner",
    "vlmproprio.answering",
    "vlmproprio.backends.registry",
    "vlmproprio.backends.reference",
    "vlmproprio.backends.openai",
    "openai",
)


def _run_cli(argv: list[str], env: dict[str, str], cwd: str, stdout: str, stderr: str) -> None:
    """The child: ``python -m vlmproprio.cli ARGV`` with its environment, folder and output files."""
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    for fd, path in ((1, stdout), (2, stderr)):
        target = os.open(path, os.O_WRONLY | os.O_TRUNC)
        os.dup2(target, fd)
        os.close(target)
    from vlmproprio import cli

    sys.argv = [cli.__file__, *argv]
    sys.exit(cli.main(argv))  # multiprocessing turns this into the exit status, as the interpreter does


def _stop_server() -> None:
    """Stop the fork server and wait for it: it has reaped every run it forked, so the CPU seconds of those runs
    count among this process's children (/usr/bin/time, resource.getrusage), as a subprocess's would."""
    stop = getattr(multiprocessing.forkserver._forkserver, "_stop", None)
    if stop is not None:
        stop()


def _context() -> multiprocessing.context.ForkServerContext:
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    # the server imports numpy (through PIL): one thread, as cli_env() gives every CLI subprocess
    old = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        if multiprocessing.forkserver._forkserver._forkserver_pid is None:
            atexit.register(_stop_server)
        multiprocessing.forkserver.ensure_running()
    finally:
        if old is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = old
    return ctx


class CliProcess:
    """A running `vlmproprio` command, with the part of ``subprocess.Popen`` the kill tests use."""

    def __init__(self, args: Sequence[object], logs: Path, env: dict[str, str] | None = None, cwd: Path = REPO):
        logs.parent.mkdir(parents=True, exist_ok=True)
        self.stdout_path, self.stderr_path = logs.with_suffix(".out"), logs.with_suffix(".err")
        for path in (self.stdout_path, self.stderr_path):
            path.write_bytes(b"")  # here, not in the child: a kill can land before it runs a line of its own
        argv = [str(a) for a in args]
        self._process = _context().Process(
            target=_run_cli,
            args=(argv, env or cli_env(), str(cwd), str(self.stdout_path), str(self.stderr_path)),
            daemon=False,
        )
        self._process.start()
        self.pid = self._process.pid

    @property
    def returncode(self) -> int | None:
        return self._process.exitcode

    def poll(self) -> int | None:
        return self._process.exitcode

    def kill(self) -> None:
        self._process.kill()  # SIGKILL

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        if self._process.exitcode is None:
            raise subprocess.TimeoutExpired(f"vlmproprio (pid {self.pid})", timeout)
        return self._process.exitcode

    def stderr(self) -> str:
        return self.stderr_path.read_text(encoding="utf-8", errors="replace")

    def stdout(self) -> str:
        return self.stdout_path.read_text(encoding="utf-8", errors="replace")


def forked_cli(args: Sequence[object], logs: Path, *, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    """``reliability_support.cli`` through the fork server: the finished command's exit status and output."""
    proc = CliProcess(args, logs, **kw)
    try:
        code = proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(30)
        raise
    return subprocess.CompletedProcess([str(a) for a in args], code, proc.stdout(), proc.stderr())
