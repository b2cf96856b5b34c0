"""JSON Schemas (draft 2020-12) of what a run folder holds, shipped with the package.

``run.json`` and every ``scores/<name>.json`` have a schema ``<name>.schema.json`` here, versioned by its
``$id`` (``.../<name>/v1.json``) and ``x-schema-version``; docs/results.md documents the fields. Load one with
``load_schema("rows")`` and check a document with any JSON Schema validator (``jsonschema``, a dependency of the package), or
``validate_run(RUN_DIR)`` which checks them all.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import load_json

SCHEMA_VERSION = 1
# file in a run folder -> schema name
RUN_FILES: dict[str, str] = {
    "run.json": "run",
    "scores/rows.json": "rows",
    "scores/aggregate.json": "aggregate",
    "scores/sweep.json": "sweep",
    "scores/sweep_aggregate.json": "sweep_aggregate",
    "scores/paired.json": "paired",
    "scores/audit.json": "audit",
    "scores/traces.json": "traces",
    "scores/meta.json": "meta",
    "scores/timing.json": "timing",
    "scores/verdicts.json": "verdicts",
    "scores/stamp.json": "stamp",
}


class SchemaError(VlmproprioError):
    """A run file that does not match its schema; the message names the file and the place."""


def schema_names() -> list[str]:
    return sorted(
        p.name.removesuffix(".schema.json")
        for p in resources.files(__name__).iterdir()
        if p.name.endswith(".schema.json")
    )


def load_schema(name: str) -> dict:
    try:
        text = resources.files(__name__).joinpath(f"{name}.schema.json").read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SchemaError(f"no schema {name!r}; known: {', '.join(schema_names())}") from None
    return json.loads(text)


def validate_run(run_dir: str | Path) -> list[str]:
    """Check every schema'd file present in ``run_dir``; returns the files checked."""
    import jsonschema

    checked = []
    for rel, name in RUN_FILES.items():
        path = Path(run_dir) / rel
        if not path.is_file():
            continue
        schema = load_schema(name)
        validator = jsonschema.Draft202012Validator(schema)
        document = load_json(path, error=SchemaError)
        errors = sorted(validator.iter_errors(document), key=lambda e: e.path)
        if errors:
            e = errors[0]
            where = "/".join(str(p) for p in e.absolute_path) or "(top)"
            raise SchemaError(f"{path}: {where}: {e.message} (schema {schema['$id']})")
        checked.append(rel)
    return checked
