"""The option vocabulary shared by the command line and the benchmark's pytest options.

One list syntax everywhere: a list option takes a comma list, may be repeated, or both
(``--model a,b`` = ``--model a --model b``). The same names, defaults and help texts in ``vlmproprio``,
``pytest benchmark/`` and tox, because both front doors take them from here.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable

from vlmproprio.errors import UsageError

# The mode default: `auto` replays a model's committed cassette when <fixtures>/responses/ has one and runs the
# model otherwise, so the benchmark is offline by default and a new model needs no extra flag. The same in the
# CLI, pytest and tox.
# What answers a request: a cassette only, the model (through the response cache), or the model with its answers
# written to the cassette (vlmproprio.answering); `auto` picks replay or live per model.
ANSWER_MODES = ("replay", "live", "record")
AUTO_MODE = "auto"
MODES = (AUTO_MODE, *ANSWER_MODES)
DEFAULT_MODE = AUTO_MODE
DEFAULT_CONDITIONS = "all"

MODEL_HELP = (
    "registry name, hf:<folder or HF repo id> or openai:<model name>; a comma list or repeated "
    "(see `vlmproprio models`)"
)
CONDITIONS_HELP = (
    "comma list (or repeated) of none, ee, joint, both, both_shuffled, both_permuted, both_noisy, state_only, "
    "primitives; "
    "or the groups paper, controls, all (default: all)"
)
EPISODES_HELP = "episode ids, a comma list or repeated (default: every episode of the fixtures)"
MODE_HELP = (
    "auto: replay the model's cassette in <fixtures>/responses/ if there is one, else live (default); "
    "replay: answers only from that cassette; live: run the model, use and fill the response cache; "
    "record: live, then write the answers to <fixtures>/responses/<model>.jsonl"
)
FIXTURES_HELP = (
    "fixture folder (default: $VLMPROPRIO_FIXTURES, else the fixtures/ of the repository the command runs in, "
    "else of the source checkout vlmproprio is installed from)"
)
CACHE_HELP = (
    "cache folder: model answers (cache.db), embeddings/, models/ (default: $VLMPROPRIO_CACHE, else the user "
    "cache directory)"
)


def split_list(values: str | Iterable[str] | None) -> list[str]:
    """Comma lists and repeated options flattened, in order, without repeats or empty items."""
    if values is None:
        return []
    items = [values] if isinstance(values, str) else list(values)
    out: list[str] = []
    for raw in items:
        # spaces around commas separate ("a, b"); a value's own spaces stay, so "door_00 " is refused as a name
        for item in re.split(r"\s*,\s*", str(raw)):
            if item and item not in out:
                out.append(item)
    return out


def check_range(name: str, value: float | None, low: float | None = None, high: float | None = None) -> None:
    """A UsageError naming the option when ``value`` is not finite or is outside [low, high] (None: unbounded)."""
    if value is None:
        return
    if not math.isfinite(value):  # NaN passes every comparison below, and inf is no setting
        raise UsageError(f"{name} must be a finite number, got {value!r} (NaN and infinity are refused)")
    if (low is not None and value < low) or (high is not None and value > high):
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        raise UsageError(f"{name} must be in [{lo}, {hi}], got {value:g}")
