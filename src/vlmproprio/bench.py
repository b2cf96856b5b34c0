"""One model's benchmark: run it for the selected cells, score the run, index the results by cell.

What ``pytest benchmark/`` does per model (vlmproprio.pytest_plugin holds only options, fixtures and test
generation): the same runner and scorer as the command line's run and score commands, with local models
pinned to one thread so a live CPU run is bit-identical to its recording.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.backends.registry import Availability, model_availability
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.conditions import parse_conditions
from vlmproprio.evaluation import score_run
from vlmproprio.models import ModelRef, resolve_model
from vlmproprio.runner import RunPlan, read_run_file, run

# pinned: bit-identical CPU runs of local models, whatever the machine's core count
BENCH_SETTINGS = BackendSettings.of(threads=1)


@dataclass
class ModelResult:
    """A model's run, scored: rows keyed by (episode, condition), the sweep, the paired table."""

    model: ModelRef
    run_dir: Path
    rows: dict[tuple[str, str], dict]
    sweep: dict[tuple[str, str], list[dict]]
    paired: list[dict]
    episodes: tuple[str, ...]
    conditions: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.model.name

    def to_json(self) -> str:
        """This result as JSON text (floats as their shortest repr, NaN as NaN: the same numbers come back)."""
        return json.dumps(
            {
                "model": self.model.name,
                "run_dir": str(self.run_dir),
                "rows": [[list(k), v] for k, v in self.rows.items()],
                "sweep": [[list(k), v] for k, v in self.sweep.items()],
                "paired": self.paired,
                "episodes": list(self.episodes),
                "conditions": list(self.conditions),
            }
        )

    @classmethod
    def from_json(cls, text: str) -> ModelResult:
        """The result :meth:`to_json` wrote (data only: nothing in it is run)."""
        doc = json.loads(text)
        return cls(
            model=resolve_model(doc["model"]),
            run_dir=Path(doc["run_dir"]),
            rows={tuple(k): v for k, v in doc["rows"]},
            sweep={tuple(k): v for k, v in doc["sweep"]},
            paired=doc["paired"],
            episodes=tuple(doc["episodes"]),
            conditions=tuple(doc["conditions"]),
        )


def availability(model: ModelRef, mode: str, fixtures: Path) -> Availability:
    """Whether ``model`` can run here in ``mode`` with the cassettes of ``fixtures``, and if not, why."""
    return model_availability(model, mode, BackendSettings(cassette_dir=Path(fixtures) / "responses"))


def run_folder(run_dir: Path, episodes: list[str], conditions: list[str]) -> Path:
    """``run_dir``, or a sibling named by a digest of the selection when a kept run there holds other episodes
    or conditions: a run folder holds one configuration and refuses another."""
    old = read_run_file(run_dir) if run_dir.is_dir() else None
    if old is None or (old.get("episodes"), old.get("conditions")) == (episodes, conditions):
        return run_dir
    digest = hashlib.sha256(json.dumps([episodes, conditions]).encode()).hexdigest()[:8]
    return run_dir.with_name(f"{run_dir.name}-{digest}")


def run_and_score(
    model: ModelRef, fixtures: Path, mode: str, episodes: Sequence[str], conditions: Sequence[str], run_root: Path
) -> ModelResult:
    """Run ``model`` over ``episodes`` x ``conditions`` (in the order given) into ``run_root``/<slug> and score it."""
    episodes = sorted(episodes)
    parsed = tuple(parse_conditions(list(conditions)))
    run_dir = run_folder(Path(run_root) / model.slug, episodes, [c.name for c in parsed])
    plan = RunPlan(
        models=(model,),
        conditions=parsed,
        fixtures=Path(fixtures),
        out=run_dir,
        episode_ids=tuple(episodes),
        mode=mode,
        backend=BENCH_SETTINGS,
        progress=False,
    )
    run(plan)
    tables = score_run(run_dir, fixtures=Path(fixtures))
    sweep: dict[tuple[str, str], list[dict]] = {}
    for r in tables.sweep:
        sweep.setdefault((r["episode_id"], r["condition"]), []).append(r)
    return ModelResult(
        model=model,
        run_dir=run_dir,
        rows={(r["episode_id"], r["condition"]): r for r in tables.rows},
        sweep=sweep,
        paired=list(tables.paired),
        episodes=tuple(episodes),
        conditions=tuple(c.name for c in parsed),
    )
