"""JSON text with one space of indent per level, exactly as ``json.dumps(obj, indent=1, ensure_ascii=False)``
writes it, mostly by the C encoder; the score files are written with it (several MB per model, where it pays:
perf/machinery.py).

With ``indent`` the standard library writes every value through its pure-Python encoder; score files are mostly
objects and arrays of plain scalars (a row, a trace, an audit span), and such a container
is written here by one call of the C encoder, whose item separator carries the newline and the indent.
Nested containers are laid out here the way ``json.dumps`` lays them out. Anything else than dicts with string
keys, lists, tuples, str, int, float, bool and None (subclasses included: numpy scalars, enums) raises
``NotPlain``, and the caller writes it with ``json.dumps``.
"""

from __future__ import annotations

import functools
import json
import math
from json.encoder import c_make_encoder, encode_basestring


class NotPlain(TypeError):
    """A value the fast writer leaves to ``json.dumps``."""


_SCALARS = frozenset({str, int, float, bool, type(None)})
_CONSTANTS = {True: "true", False: "false", None: "null"}


def _not_plain(obj):
    raise NotPlain(f"{type(obj).__name__} is not a plain JSON value")


@functools.lru_cache(maxsize=64)
def _flat_encoder(depth: int, allow_nan: bool):
    """Encodes a container of scalars as ``[`` items joined by ``,`` newline and ``depth`` spaces ``]``.

    The C encoder is called directly when there is one (``JSONEncoder.encode`` builds a new one per call, which
    costs as much as encoding a row); its arguments are those ``JSONEncoder.iterencode`` passes it."""
    separator = ",\n" + " " * depth
    if c_make_encoder is not None:
        encode = c_make_encoder(None, _not_plain, encode_basestring, None, ": ", separator, False, False, allow_nan)
        return lambda obj: "".join(encode(obj, 0))
    return json.JSONEncoder(ensure_ascii=False, allow_nan=allow_nan, separators=(separator, ": ")).encode


def _float_text(x: float, nan_as_null: bool) -> str:
    if math.isfinite(x):
        return float.__repr__(x)
    if nan_as_null:
        return "null"
    return "NaN" if x != x else "Infinity" if x > 0 else "-Infinity"


def _scalar_text(x, nan_as_null: bool) -> str:
    t = type(x)
    if t is str:
        return encode_basestring(x)
    if t is float:
        return _float_text(x, nan_as_null)
    if t is int:
        return int.__repr__(x)
    if t is bool or x is None:
        return _CONSTANTS[x]
    raise NotPlain(f"{t.__name__} is not a plain JSON value")


def _flat(obj, depth: int, nan_as_null: bool) -> str | None:
    """The items of a container of scalars in one C-encoder call; None when a float is not finite and must
    be written as null (the encoder cannot), or when an item is not a plain scalar."""
    values = obj.values() if type(obj) is dict else obj
    if not all(type(v) in _SCALARS for v in values):
        return None
    try:
        return _flat_encoder(depth, not nan_as_null)(obj)[1:-1]
    except ValueError:  # allow_nan=False met NaN or an infinity
        return None


def _write(obj, depth: int, out: list[str], nan_as_null: bool) -> None:
    t = type(obj)
    if t is not dict and t is not list and t is not tuple:
        out.append(_scalar_text(obj, nan_as_null))
        return
    if t is dict and not all(type(k) is str for k in obj):
        raise NotPlain("a dict with keys that are not strings")
    opening, closing = ("{", "}") if t is dict else ("[", "]")
    if not obj:
        out.append(opening + closing)
        return
    pad = " " * (depth + 1)
    body = _flat(obj, depth + 1, nan_as_null)
    if body is not None:
        out.append(f"{opening}\n{pad}{body}\n{' ' * depth}{closing}")
        return
    out.append(f"{opening}\n{pad}")
    separator = ",\n" + pad
    for i, item in enumerate(obj.items() if t is dict else obj):
        if i:
            out.append(separator)
        if t is dict:
            out.append(encode_basestring(item[0]) + ": ")
            item = item[1]
        _write(item, depth + 1, out, nan_as_null)
    out.append(f"\n{' ' * depth}{closing}")


def dumps_indented(obj, *, nan_as_null: bool = False) -> str:
    """``json.dumps(obj, indent=1, ensure_ascii=False)``, or with ``nan_as_null`` the same with every non-finite
    float written as null (as the score files are); ``NotPlain`` for values it leaves to ``json.dumps``."""
    out: list[str] = []
    _write(obj, 0, out, nan_as_null)
    return "".join(out)
