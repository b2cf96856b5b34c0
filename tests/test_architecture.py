"""Data flows one way: no module imports a later stage (docs/architecture.md lists the stages).

Every ``import vlmproprio.x`` / ``from vlmproprio.x import`` in a module counts, lazy imports inside
functions included; imports under ``if TYPE_CHECKING:`` are annotations only and do not.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "vlmproprio"

# Stage of every module (dotted, relative to vlmproprio); a module may import its own stage or earlier ones.
STAGES: list[tuple[str, ...]] = [
    ("errors", "secrets", "io", "json_text", "parallel", "stores", "locations", "digests", "options", "schemas"),
    ("primitives", "episodes", "chat", "kinds", "models"),
    ("summary", "record"),
    ("conditions",),
    ("prompts",),
    ("cache", "cassettes"),
    ("backends", "testing"),
    ("answering",),
    ("transcripts", "parsing"),
    ("pipeline",),
    ("runner", "show", "run_folder", "preview"),
    ("scoring", "embeddings", "segmentation"),
    ("stats", "power"),
    ("verdicts", "sanity"),
    ("evaluation", "sidecars"),  # evaluation/: its own order, EVALUATION_ORDER below
    ("report",),
    ("dataset_export", "inspect"),
    ("bench", "api"),
    ("cli", "pytest_plugin"),
]


def stage_of(module: str) -> int:
    top = module.split(".")[0]
    for i, names in enumerate(STAGES):
        if top in names:
            return i
    raise AssertionError(f"module vlmproprio.{module} is in no stage: add it to STAGES and docs/architecture.md")


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        if parts:
            out.append((".".join(parts), path))
    return out


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    return skip


def imported_stages(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    skip = _type_checking_nodes(tree)
    found = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "vlmproprio":
                found += [a.name for a in node.names]
            elif node.module.startswith("vlmproprio."):
                found.append(node.module[len("vlmproprio.") :])
        elif isinstance(node, ast.Import):
            found += [a.name[len("vlmproprio.") :] for a in node.names if a.name.startswith("vlmproprio.")]
    return found


@pytest.mark.parametrize(("module", "path"), _modules(), ids=[m for m, _ in _modules()])
def test_no_module_imports_a_later_stage(module: str, path: Path) -> None:
    mine = stage_of(module)
    later = [m for m in imported_stages(path) if m != "__version__" and stage_of(m) > mine]
    assert not later, f"vlmproprio.{module} (stage {mine}) imports later stage(s): {', '.join(later)}"


# A package is one stage whose modules import each other one way too, in the order data flows through them: a
# module imports only siblings before it, each by its own path (never the package, whose __init__ imports all).
PACKAGE_ORDERS: dict[str, tuple[str, ...]] = {
    # the order score_run runs them in
    "evaluation": (
        "metrics",
        "definitions",
        "formats",
        "inputs",
        "captions",
        "cells",
        "out_of_sample",
        "chance",
        "tables",
        "statistics",
        "controls",
        "meta",
        "judge",
        "frame_table",
        "generations",
        "run",
    ),
    # metrics needs no trace: it scores points, wherever they come from
    "segmentation": ("trace", "metrics", "chance", "sweep"),
    "scoring": ("lexicon", "expectation", "matching", "rubric", "judge"),
    "episodes": ("types", "pixels", "manifest", "store"),
    "embeddings": ("encoder", "store", "sidecar", "embedder"),
    "parsing": ("common", "reasoning", "wrappers", "frame_lines", "frames", "single"),
}
EVALUATION_ORDER = PACKAGE_ORDERS["evaluation"]


def sibling_imports(package: str, path: Path) -> list[str]:
    """The modules of ``package`` that ``path`` imports; ``"__init__"`` for the package itself."""
    order = PACKAGE_ORDERS[package]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == f"vlmproprio.{package}":
            found += [a.name if a.name in order else "__init__" for a in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith(f"vlmproprio.{package}."):
            found.append(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            found += [a.name.split(".")[2] for a in node.names if a.name.startswith(f"vlmproprio.{package}.")]
    return found


@pytest.mark.parametrize("package", sorted(PACKAGE_ORDERS))
def test_every_module_of_a_package_has_a_place_in_its_order(package: str) -> None:
    modules = {p.stem for p in (SRC / package).glob("*.py") if p.stem != "__init__"}
    assert modules == set(PACKAGE_ORDERS[package])


@pytest.mark.parametrize(
    ("package", "name"), [(p, n) for p, order in sorted(PACKAGE_ORDERS.items()) for n in order], ids=str
)
def test_no_module_of_a_package_imports_a_later_sibling(package: str, name: str) -> None:
    order = PACKAGE_ORDERS[package]
    found = sibling_imports(package, SRC / package / f"{name}.py")
    later = [m for m in found if m == "__init__" or order.index(m) >= order.index(name)]
    assert not later, f"vlmproprio.{package}.{name} imports {', '.join(later)} (only modules before it)"


# Packages that are one module's API split by concern: their __init__ re-exports every public name. The others
# (evaluation, parsing) export a chosen API and keep their helpers to themselves.
FACADES = ("embeddings", "episodes", "scoring", "segmentation")


@pytest.mark.parametrize("package", FACADES)
def test_a_package_with_all_re_exports_every_public_name_of_its_modules(package: str) -> None:
    """Callers import from the package alone, so a module can move inside it without touching them."""
    import importlib

    pkg = importlib.import_module(f"vlmproprio.{package}")
    missing = []
    for name in PACKAGE_ORDERS[package]:
        module = importlib.import_module(f"vlmproprio.{package}.{name}")
        public = {
            n
            for n, v in vars(module).items()
            if not n.startswith("_") and getattr(v, "__module__", "") == module.__name__
        }
        public |= {n for n in vars(module) if n.isupper() and not n.startswith("_") and n != "TYPE_CHECKING"}
        missing += [
            f"{name}.{n}"
            for n in sorted(public)
            if getattr(pkg, n, None) is not getattr(module, n) or n not in pkg.__all__
        ]
    assert not missing, f"vlmproprio.{package} does not re-export: {', '.join(missing)}"


# ---------------------------------------------------------------------------------------------- shape rules

MAX_MODULE_LINES = 500
# modules that are data tables (one entry per line), not logic: exempt from the size rule
DATA_MODULES: set[str] = set()


def test_no_module_is_longer_than_500_lines() -> None:
    long = []
    for module, path in _modules():
        lines = len(path.read_text().splitlines())
        if lines > MAX_MODULE_LINES and module not in DATA_MODULES:
            long.append(f"vlmproprio.{module} ({lines} lines)")
    assert not long, "split these by concern: " + ", ".join(long)


MAX_FUNCTION_LINES = 80
# functions that are data tables (one entry per line), not logic: exempt from the length rule
DATA_TABLES: set[str] = set()


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node


def test_no_function_is_longer_than_80_lines() -> None:
    long = []
    for module, path in _modules():
        for fn in _functions(ast.parse(path.read_text())):
            lines = fn.end_lineno - fn.lineno + 1
            if lines > MAX_FUNCTION_LINES and f"{module}.{fn.name}" not in DATA_TABLES:
                long.append(f"vlmproprio.{module}.{fn.name} ({lines} lines)")
    assert not long, "split these into named steps: " + ", ".join(long)


# what a model name's syntax is made of: only vlmproprio.models reads it, and a prefix is spelled once, in the
# KindSpec its backend module registers (vlmproprio.kinds)
MODEL_NAME_SYNTAX = ("TINY_PREFIX", '"tiny:"', "_check_name")


def _kind_prefixes() -> set[str]:
    from vlmproprio.kinds import kind_specs

    return {spec.prefix for spec in kind_specs() if spec.prefix}


def _declared_prefixes(tree: ast.AST) -> set[int]:
    """The ``prefix=`` constants of KindSpec(...) calls: where a prefix may be spelled."""
    return {
        id(kw.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and ast.unparse(node.func).endswith("KindSpec")
        for kw in node.keywords
        if kw.arg == "prefix"
    }


def _spelled_prefixes(path: Path, prefixes: set[str]) -> list[int]:
    tree = ast.parse(path.read_text())
    declared = _declared_prefixes(tree)
    return [
        node.lineno
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and node.value in prefixes and id(node) not in declared
    ]


def test_a_model_name_is_parsed_in_one_place() -> None:
    prefixes = _kind_prefixes()
    assert {"hf:", "openai:"} <= prefixes
    offenders = []
    for module, path in _modules():
        if module == "models":
            continue
        text = path.read_text()
        offenders += [f"vlmproprio.{module}: {s}" for s in MODEL_NAME_SYNTAX if s in text]
        offenders += [f"vlmproprio.{module}:{n} a prefix" for n in _spelled_prefixes(path, prefixes)]
    assert not offenders, "parse model names with vlmproprio.models.resolve_model: " + ", ".join(offenders)


def test_backends_are_discovered_in_one_place() -> None:
    """Only vlmproprio.kinds imports modules by name (the stage test cannot see such imports)."""
    found = [
        f"vlmproprio.{module}"
        for module, path in _modules()
        # backends.python imports the user's own factory (py:package.module:factory), never a vlmproprio module
        if module not in ("kinds", "backends.python")
        and ("import_module(" in path.read_text() or "__import__(" in path.read_text())
    ]
    assert not found, "modules imported by name outside vlmproprio.kinds: " + ", ".join(found)


BACKEND_API = {"identity", "generate", "plan_batches", "calls_model", "max_batch_size", "close"}


def test_backend_capabilities_are_declared_not_probed() -> None:
    """backends.base.Backend declares its capabilities: code asks them, it does not getattr-probe them."""
    probes = []
    for module, path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in ("getattr", "hasattr")
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and node.args[1].value in BACKEND_API
            ):
                probes.append(f"vlmproprio.{module}:{node.lineno} {ast.unparse(node)}")
    assert not probes, "capability probes: " + "; ".join(probes)
