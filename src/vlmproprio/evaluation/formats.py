"""How score tables are written: JSON without NaN (None instead), and CSV with floats as repr."""

from __future__ import annotations

import csv
import io
import json
import math

from vlmproprio.json_text import NotPlain, dumps_indented


def _json_safe(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def dumps_json(obj) -> str:
    try:
        # the same text as below, written mostly by the C encoder (the score files are ~9 MB per model)
        return dumps_indented(obj, nan_as_null=True) + "\n"
    except NotPlain:  # numpy scalars, non-string keys, ...
        return json.dumps(_json_safe(obj), indent=1, ensure_ascii=False, allow_nan=False) + "\n"


def dumps_csv(rows: list[dict]) -> str:
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow(["" if r.get(c) is None else repr(r[c]) if isinstance(r[c], float) else r[c] for c in cols])
    return buf.getvalue()
