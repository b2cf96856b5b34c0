"""The real CLI in a real process, without paying Python's start-up in every one of them.

Kill tests start dozens of `vlmproprio` processes and SIGKILL them: the separate process is the point, but
each ``python -m vlmproprio.cli`` spends most of its CPU importing (the openai SDK alone is ~1 s, the report's
matplotlib ~1 s), which says nothing about kills. ``CliProcess`` forks each command from a multiprocessing
fork server that imported those modules once (imports only: no file, database or thread is open when it
forks), so every command is still its own process, with its own PID, environment, working folder, stdout
and stderr (whole file descriptors: whatever a library or a traceback writes is captured), killed by the
kernel with exit status -9, running the same ``vlmproprio.cli.main`` that ``python -m vlmproprio.cli`` runs,
after the same ``python -c`` prelude where one is given, and exiting through the same interpreter shut-down
(non-daemon threads joined, streams flushed, the return value as the exit status).

The fork server re-imports nothing of the test process but this module: a test run from a script must guard
it with ``if __name__ == "__main__"`` (``python -m pytest`` and the ``pytest`` script do).
"""

from __future__ import annotations

import atexit
import itertools
import multiprocessing
import multiprocessing.forkserver
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from reliability_support import REPO, cli_env

# What `vlmproprio run` (reference and openai backends), `score` (embeddings cached), `report` and `compare`
# import, imported once in the fork server. Not torch: forking a process that holds it costs ~0.15 s of CPU
# a fork (page tables, copy-on-write faults), more than it saves where only a few commands embed captions.
PRELOAD = (
    "vlmproprio.cli",
    "vlmproprio.runner",
    "vlmproprio.answering",
    "vlmproprio.backends.registry",
    "vlmproprio.backends.reference",
    "vlmproprio.backends.openai",
    "vlmproprio.locations",
    "vlmproprio.evaluation.run",
    "vlmproprio.evaluation.generations",
    "vlmproprio.report",
    "vlmproprio.report.build",
    "vlmproprio.report.compare",
    "vlmproprio.report.power_section",
    "openai",
    "diskcache",
    "tqdm",
    "PIL.Image",
    "PIL.PngImagePlugin",
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
)

_numbers = itertools.count()


def _run_cli(argv: list[str], env: dict[str, str], cwd: str, outputs: tuple[str, str], prelude: str | None) -> None:
    """The child: ``python [-c PRELUDE] -m vlmproprio.cli ARGV`` with its environment, folder and outputs."""
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    for fd, path in zip((1, 2), outputs, strict=True):
        target = os.open(path, os.O_WRONLY | os.O_TRUNC)
        os.dup2(target, fd)
        os.close(target)
    from vlmproprio import cli

    sys.argv = [cli.__file__, *argv]
    if prelude is not None:
        exec(compile(prelude, "<string>", "exec"), {"__name__": "__main__"})
    sys.exit(cli.main(argv))  # multiprocessing turns this into the exit status, as the interpreter does


def _stop_server() -> None:
    """Stop the fork server and wait for it: it has reaped every command it forked, so their CPU seconds count
    among this process's children (/usr/bin/time, resource.getrusage), as a subprocess's would."""
    stop = getattr(multiprocessing.forkserver._forkserver, "_stop", None)
    if stop is not None:
        stop()


def fork_context() -> multiprocessing.context.ForkServerContext:
    """The multiprocessing context whose processes are forked from the import-once server (started here)."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    if multiprocessing.forkserver._forkserver._forkserver_pid is not None:
        return ctx
    # the server imports numpy: one thread, as cli_env() gives every CLI subprocess
    old = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        atexit.register(_stop_server)
        multiprocessing.forkserver.ensure_running()
    finally:
        if old is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = old
    return ctx


class CliProcess:
    """A running `vlmproprio` command, with the part of ``subprocess.Popen`` the kill tests use; its stdout and
    stderr go to files in ``logs`` (a folder of the test's own)."""

    def __init__(
        self,
        args: Sequence[object],
        logs: Path,
        *,
        env: dict[str, str] | None = None,
        cwd: Path = REPO,
        python_prelude: str | None = None,
    ):
        logs.mkdir(parents=True, exist_ok=True)
        n = next(_numbers)
        self.stdout_path, self.stderr_path = logs / f"cli-{os.getpid()}-{n}.out", logs / f"cli-{os.getpid()}-{n}.err"
        for path in (self.stdout_path, self.stderr_path):
            path.write_bytes(b"")  # here, not in the child: a kill can land before it runs a line of its own
        self.args = [str(a) for a in args]
        outputs = (str(self.stdout_path), str(self.stderr_path))
        self._process = fork_context().Process(
            target=_run_cli, args=(self.args, env or cli_env(), str(cwd), outputs, python_prelude)
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
    return subprocess.CompletedProcess(proc.args, code, proc.stdout(), proc.stderr())
