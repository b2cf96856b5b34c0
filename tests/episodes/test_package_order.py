"""Inside vlmproprio.episodes data flows one way too: types -> pixels -> manifest -> store."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "src" / "vlmproprio" / "episodes"
ORDER = ("types", "pixels", "manifest", "store")


def _inside_imports(path: Path) -> list[str]:
    """The package's modules that ``path`` imports (``vlmproprio.episodes.x`` or ``from vlmproprio.episodes
    import x``); importing the package itself counts as importing all of it."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "vlmproprio.episodes":
            found += [a.name if a.name in ORDER else "__init__" for a in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("vlmproprio.episodes."):
            found.append(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            found += [a.name.split(".")[2] for a in node.names if a.name.startswith("vlmproprio.episodes.")]
    return found


def test_every_module_has_a_place_in_the_order() -> None:
    assert {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"} == set(ORDER)


@pytest.mark.parametrize("name", ORDER)
def test_no_module_imports_a_later_one(name: str) -> None:
    mine = ORDER.index(name)
    later = [m for m in _inside_imports(PACKAGE / f"{name}.py") if m not in ORDER or ORDER.index(m) > mine]
    assert not later, f"vlmproprio.episodes.{name} imports later module(s): {', '.join(later)}"
