"""vlmproprio.scoring is one package whose modules import each other one way, and whose __init__ re-exports every
public name, so callers import from ``vlmproprio.scoring`` alone."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

import vlmproprio.scoring as scoring
from test_architecture import imported_stages

PACKAGE = Path(scoring.__file__).parent
# the order data flows in: a module may import only the ones before it
ORDER = ("lexicon", "expectation", "matching", "rubric", "judge")


def test_every_scoring_module_has_a_place_in_the_order():
    assert {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"} == set(ORDER)


@pytest.mark.parametrize("name", ORDER)
def test_no_scoring_module_imports_a_later_one(name):
    inside = [m.split(".")[1] for m in imported_stages(PACKAGE / f"{name}.py") if m.startswith("scoring.")]
    later = [m for m in inside if ORDER.index(m) >= ORDER.index(name)]
    assert not later, f"vlmproprio.scoring.{name} imports {', '.join(later)}"


@pytest.mark.parametrize("name", ORDER)
def test_the_package_re_exports_every_public_name(name):
    module = importlib.import_module(f"vlmproprio.scoring.{name}")
    public = {
        n for n, v in vars(module).items() if not n.startswith("_") and getattr(v, "__module__", "") == module.__name__
    }
    public |= {n for n in vars(module) if n.isupper() and not n.startswith("_")}
    missing = sorted(n for n in public if getattr(scoring, n, None) is not getattr(module, n))
    assert not missing, f"vlmproprio.scoring does not re-export {', '.join(missing)} of scoring.{name}"
    assert set(public) <= set(scoring.__all__)
