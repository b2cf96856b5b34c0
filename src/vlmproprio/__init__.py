"""vlmproprio: does proprioception make a VLM's captions and subtask segmentations of robot episodes better?

From Python: ``vlmproprio.evaluate(model=..., episodes=..., conditions=..., out=...)`` (vlmproprio.api), imported
on first use so that ``import vlmproprio`` stays light.
"""

# the C module: signal.py imports enum, a few ms in which Ctrl-C would still be a traceback
import _signal
import sys as _sys

__version__ = "0.1.0"
__all__ = ["evaluate"]


def _is_the_command() -> bool:
    """Whether this process is the ``vlmproprio`` command (the console script or ``python -m vlmproprio.cli``)
    rather than a program importing the package."""
    argv0 = _sys.argv[0] if _sys.argv else ""
    if argv0.replace("\\", "/").rsplit("/", 1)[-1].removesuffix(".exe") == "vlmproprio":
        return True
    orig = getattr(_sys, "orig_argv", [])
    return any(orig[i] == "-m" and orig[i + 1] == "vlmproprio.cli" for i in range(len(orig) - 1))


def _interrupted_while_starting(signum, frame) -> None:
    """Ctrl-C while the command's modules are imported (the first ~0.2 s, before ``main`` can catch it): one line
    and exit status 130, as later, not a traceback through the import machinery."""
    import os  # already imported by the interpreter's start-up

    os.write(2, b"vlmproprio: interrupted\n")
    # Not an exception: raised inside a C extension's initialisation (numpy's) it would come out as an ImportError.
    # Nothing has been written yet, so there is nothing to clean up.
    os._exit(130)


def _end_of_start() -> None:
    """Called by vlmproprio.cli once its modules are imported: ``main`` handles Ctrl-C from here on."""
    if _signal.getsignal(_signal.SIGINT) is _interrupted_while_starting:
        _signal.signal(_signal.SIGINT, _signal.default_int_handler)


# Installed here, the first module of ours the command imports, and only in the command: a program that imports
# the package keeps its own Ctrl-C behaviour.
if _is_the_command() and _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:
    try:  # noqa: SIM105 (contextlib would cost an import in the window this covers)
        _signal.signal(_signal.SIGINT, _interrupted_while_starting)
    except ValueError:  # not the main thread
        pass


def __getattr__(name: str):
    if name == "evaluate":
        from vlmproprio.api import evaluate

        return evaluate
    raise AttributeError(f"module 'vlmproprio' has no attribute {name!r}")
