"""The report's power section: what this run's episode structure can detect at the run's corrected alpha.

The same simulation as `vlmproprio power` (vlmproprio.power), with the run's own numbers of episodes per task and
the alpha and family size of the primary hypotheses the run was scored against, so a "not supported" or
"inconclusive" verdict can be read against the smallest effect the run could have found.
"""

from __future__ import annotations

from pathlib import Path

from vlmproprio import power
from vlmproprio.report.data import RunScores
from vlmproprio.report.plots import Plot
from vlmproprio.report.tables import Table

POWER_PLOT = "power_curves.png"


def run_groups(s: RunScores) -> dict[str, int]:
    """Episodes per task in the run, and all of them pooled (the verdicts' task groups)."""
    by_task: dict[str, set[str]] = {}
    for r in s.rows:
        by_task.setdefault(r["task"], set()).add(r["episode_id"])
    groups = {task: len(ids) for task, ids in sorted(by_task.items())}
    groups["all"] = sum(groups.values())
    return groups


def run_power(s: RunScores, cache_dir: Path | None = None) -> power.PowerAnalysis:
    """The analysis for the run's groups, alpha and family; kept in ``cache_dir`` (see power.analyse_cached)."""
    claims = s.verdicts.get("claims", {})
    family = len(claims.get("primary", [])) or power.PowerSettings().family
    settings = power.PowerSettings(alpha=float(claims.get("alpha", power.PowerSettings().alpha)), family=family)
    return power.analyse_cached(settings, run_groups(s), cache_dir)


def _fmt(v: float | None) -> str:
    return "never" if v is None else f"{v:.2f}"


def power_table(a: power.PowerAnalysis) -> Table:
    rows = [
        [
            g,
            str(n),
            _fmt(a.mde_rate["0"][g]),
            _fmt(a.mde_rate["0.3"][g]),
            _fmt(a.mde_shift_sd[g]),
            _fmt(a.f1["mde"][g]),
        ]
        for g, n in a.groups.items()
    ]
    w, c = a.words, a.correctness
    need_w = "more than 1000" if w["episodes_needed"] is None else str(w["episodes_needed"])
    need_c = "more than 1000" if c["episodes_needed"] is None else str(c["episodes_needed"])
    st = a.settings
    return Table(
        title="What this run can detect: minimal effects at 80 % power",
        headers=[
            "task",
            "episodes",
            "rate with state (never right without)",
            "rate with state (right 30 % without)",
            "continuous effect (SD)",
            f"boundary-F1 lift (SD {a.f1['sd']:g})",
        ],
        rows=rows,
        align=["l", "r", "r", "r", "r", "r"],
        note=f"Simulated with the suite's own paired test (exact sign-flip) at alpha / family = {st['alpha']:g} / "
        f"{st['family']} = {st['level']:.4f}, Holm's first step (a lower bound on the power under Holm), "
        f"{st['n_sims']} data sets per point, paired by episode. The paper's word counts ({w['from']:g} → "
        f"{w['to']:g}, per-episode SD {w['sd']:g} assumed) need {need_w} paired episodes for 80 % power; a "
        f"correctness of {c['p']:g} with state against {c['q']:g} without needs {need_c}. An effect smaller than "
        "these is not ruled out by a verdict that is not 'supported'. `vlmproprio power` sets the assumptions.",
        anchor="power",
    )


def power_cache(cache_root: str | Path | None, fixtures: str | Path | None) -> Path | None:
    """``<cache root>/power`` (default root: vlmproprio.locations), None when it would lie in the fixture folder
    (where a new file breaks the manifest): the analysis is then computed, not kept."""
    from vlmproprio.locations import cache_root as default_root
    from vlmproprio.locations import is_inside

    folder = (Path(cache_root) if cache_root is not None else default_root()) / power.POWER_CACHE_DIR
    return None if fixtures and Path(fixtures).is_dir() and is_inside(folder, Path(fixtures)) else folder


def power_outputs(s: RunScores, out: Path, cache_dir: Path | None) -> tuple[Plot, Table]:
    """The power curves (a PNG in ``out``) and the minimal-detectable-effect table for a scored run; the
    analysis is kept in ``cache_dir`` (``power_cache``) for the next report with the same episode structure."""
    a = run_power(s, cache_dir)
    power.plot_power_curves(a, out / POWER_PLOT)
    plot = Plot(
        "all",
        "power",
        POWER_PLOT,
        "Power of the paired test with this run's episodes",
        "Probability that a primary hypothesis is detected (after correction) as a function of the true effect: "
        "a correctness rate with state against never right / right 30 % of the time without (left two panels), a "
        "shift in units of the per-episode SD such as a boundary-F1 lift or a word count (right), per task and "
        "pooled; dashed: 80 %.",
    )
    return plot, power_table(a)
