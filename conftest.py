"""The benchmark's pytest options, short spellings: ``pytest benchmark/ --model NAME --mode replay``.

At the repository root so that it loads for every pytest run in the repository (``pytest --model reference``
runs the whole suite with that model; ``pytest /path/to/repo/benchmark ...`` works from any folder).

The plugin itself (vlmproprio.pytest_plugin) is registered here rather than through an entry point, so installing
vlmproprio changes no other project's pytest; its long names (``--vlmproprio-model``) stay usable with
``pytest -p vlmproprio.pytest_plugin`` anywhere.
"""

from __future__ import annotations

import pytest

from vlmproprio import pytest_plugin


def pytest_addoption(parser: pytest.Parser, pluginmanager: pytest.PytestPluginManager) -> None:
    # registered once: an environment with an older install (pytest11 entry point) has it already
    if not pluginmanager.is_registered(pytest_plugin):
        pluginmanager.register(pytest_plugin, "vlmproprio")
    pytest_plugin.add_options(parser, short=True)


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook; without xdist installed it is never called
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: what the benchmark's plugin decides where it decides (one process for the benchmark alone,
    and for runs that record, run live or keep their run folder), else one worker more than there are cores.

    The plugin is asked first because this hook returns the first answer and this conftest's implementation is
    called before the plugin's: answering alone, it would override the plugin, and `pytest benchmark/ --mode
    record` would start workers that record the same cassette at once. About a tenth of the suite's time is spent
    waiting (on CLI subprocesses, local servers, SIGKILLed runs), which the extra worker fills (on 2 cores,
    3 workers take about a tenth less time than 2)."""
    import os

    decided = pytest_plugin.pytest_xdist_auto_num_workers(config)
    return decided if decided is not None else (os.cpu_count() or 1) + 1
