"""Robot state as prompt text, and back.

Every number is written with a fixed 3 decimal places (rad for angles, m for
positions and the gripper opening), so equal states give equal text and equal
cache keys on every machine. A frame's state is one line::

    Frame 3: joint angles [0.012, 0.301, -0.015, -2.310, 0.010, 2.614, 0.785, 0.080]; end-effector [0.102, -0.003, 1.012, 3.139, 0.005, 1.571]

with either part left out when the condition does not give it. The reference
backend reads these lines back with ``parse_state_lines``; that is the only
thing it reads.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

DECIMALS = 3
JOINT_LABEL = "joint angles"
EE_LABEL = "end-effector"

_LINE_RE = re.compile(r"^Frame (\d+):(.*)$", re.MULTILINE)
_VEC_RE = {
    "joints": re.compile(re.escape(JOINT_LABEL) + r" \[([^\]]*)\]"),
    "ee": re.compile(re.escape(EE_LABEL) + r" \[([^\]]*)\]"),
}


def format_number(x: float) -> str:
    if not math.isfinite(x):
        raise ValueError(f"state value {x!r} is not finite")
    s = f"{x:.{DECIMALS}f}"
    return "0.000" if s == "-0.000" else s  # one text for zero, whatever its sign


_VECTOR_TEXT: dict[tuple, str] = {}  # a run writes each frame's state under several conditions and prompts
_MAX_REMEMBERED = 1 << 16


def format_vector(values: Sequence[float]) -> str:
    key = tuple(values)  # equal numbers (0.0 and -0.0 too) give equal text; a NaN never equals itself here
    text = _VECTOR_TEXT.get(key)
    if text is None:
        text = "[" + ", ".join(format_number(float(v)) for v in key) + "]"
        if len(_VECTOR_TEXT) < _MAX_REMEMBERED:
            _VECTOR_TEXT[key] = text
    return text


def format_state_line(
    number: int, joints: Sequence[float] | None, ee: Sequence[float] | None, words: str | None = None
) -> str:
    """One frame's state; ``words`` replaces the numbers for the `primitives` control."""
    parts = []
    if joints is not None:
        parts.append(f"{JOINT_LABEL} {format_vector(joints)}")
    if ee is not None:
        parts.append(f"{EE_LABEL} {format_vector(ee)}")
    if words is not None:
        parts.append(words)
    return f"Frame {number}: " + "; ".join(parts)


@dataclass(frozen=True)
class ParsedState:
    number: int
    joints: tuple[float, ...] | None
    ee: tuple[float, ...] | None


@lru_cache(maxsize=_MAX_REMEMBERED)  # the reference captioner reads the same state lines in many prompts
def _floats(s: str) -> tuple[float, ...] | None:
    try:
        vals = tuple(float(t) for t in s.split(","))
    except ValueError:
        return None
    return vals if all(math.isfinite(v) for v in vals) else None


def parse_state_lines(text: str) -> list[ParsedState]:
    """All ``Frame N: ...`` state lines in a prompt, in order of appearance."""
    return list(_parse_state_text(text))


# a replay meets each frame's state text ~12 times (stages and prompts): ~2,000 distinct texts per model; the
# bound keeps a long-lived process (a benchmark session) from holding every prompt section it ever read
@lru_cache(maxsize=1 << 12)
def _parse_state_text(text: str) -> tuple[ParsedState, ...]:
    out = []
    for m in _LINE_RE.finditer(text):
        rest = m.group(2)
        vecs = {}
        for name, rx in _VEC_RE.items():
            v = rx.search(rest)
            vecs[name] = _floats(v.group(1)) if v else None
        if vecs["joints"] is None and vecs["ee"] is None:
            continue
        out.append(ParsedState(int(m.group(1)), vecs["joints"], vecs["ee"]))
    return tuple(out)
