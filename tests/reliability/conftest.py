"""The reliability suite's figures: each test reports what it tried and what survived; the session prints them.

``figures(name, trials=..., faults=..., lost=0, ...)`` records one line; lines of the same name (one per
parametrised case) are added up. The terminal summary lists them under "reliability figures", so a CI log
shows the numbers behind docs/reliability.md on every run.
"""

from __future__ import annotations

import pytest

_FIGURES: dict[str, dict[str, object]] = {}


@pytest.fixture
def figures(request):
    def record(name: str | None = None, **numbers: object) -> None:
        line = _FIGURES.setdefault(name or request.node.name, {})
        for key, value in numbers.items():
            old = line.get(key)
            summable = isinstance(value, int) and isinstance(old, int) and not isinstance(value, bool)
            line[key] = old + value if summable else value

    return record


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    if not _FIGURES:
        return
    terminalreporter.section("reliability figures")
    for name, numbers in _FIGURES.items():
        terminalreporter.write_line(f"{name}: " + ", ".join(f"{k}={v}" for k, v in numbers.items()))
