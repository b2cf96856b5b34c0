"""The power analysis simulates exactly the suite's paired test, and agrees with closed forms."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from vlmproprio.cli import main
from vlmproprio.power import (
    PowerSettings,
    analyse,
    exact_rate_power,
    mc_error,
    rate_mde,
    sign_flip_p_many,
    simulate_rate_power,
    simulate_shift_power,
)
from vlmproprio.stats import sign_flip_p


@pytest.mark.parametrize("n", [1, 3, 10, 12, 17, 22])
def test_vectorised_test_is_the_suites_test(n):
    rng = np.random.default_rng(n)
    d = np.round(rng.normal(0.2, 1.0, size=(12, n)), 3)
    d[:4] = rng.integers(-1, 2, size=(4, n))  # rates: many ties, the hard case for a re-implementation
    d[4] = 0.0
    expected = [sign_flip_p(row)[0] for row in d]
    assert sign_flip_p_many(d).tolist() == expected


def test_closed_form_equals_the_suites_test_over_every_outcome():
    """Brute force for 5 episodes: every outcome in {-1, 0, 1}^5, its probability, stats.sign_flip_p."""
    n, p, q, level = 5, 0.9, 0.2, 0.07
    up, down, same = p * (1 - q), q * (1 - p), 1 - p * (1 - q) - q * (1 - p)
    prob = {1: up, -1: down, 0: same}
    brute = 0.0
    for d in itertools.product((-1, 0, 1), repeat=n):
        arr = np.array(d, dtype=float)
        if arr.mean() > 0 and sign_flip_p(arr)[0] < level:
            brute += float(np.prod([prob[v] for v in d]))
    assert exact_rate_power(n, p, q, level) == pytest.approx(brute, abs=1e-12)


@pytest.mark.parametrize(("n", "p", "q"), [(10, 0.8, 0.0), (12, 0.7, 0.1), (12, 0.95, 0.3), (22, 0.45, 0.05)])
def test_simulation_matches_the_closed_form_within_monte_carlo_error(n, p, q):
    settings = PowerSettings(n_sims=2000)
    exact = exact_rate_power(n, p, q, settings.level)
    sim = simulate_rate_power(n, p, q, settings)
    # n = 22 uses the suite's 20 000 random sign patterns, not all of them: allow their own small error
    slack = 4 * mc_error(exact, settings.n_sims) + (0.01 if n > settings.max_exact else 0.0)
    assert abs(sim - exact) <= slack, (sim, exact)


def test_no_effect_is_detected_at_most_at_the_corrected_level():
    settings = PowerSettings(n_sims=4000)
    for n in (10, 12):
        assert simulate_shift_power(n, 0.0, settings) <= settings.level / 2 + 4 * mc_error(settings.level, 4000)
        assert exact_rate_power(n, 0.3, 0.3, settings.level) <= settings.level / 2


def test_seeded_and_independent_of_what_else_is_asked():
    s = PowerSettings(n_sims=200)
    a = simulate_shift_power(12, 0.8, s)
    simulate_rate_power(12, 0.5, 0.0, s)
    assert simulate_shift_power(12, 0.8, s) == a
    assert simulate_shift_power(12, 0.8, PowerSettings(n_sims=200, seed=1)) != a or a in (0.0, 1.0)


def test_minimal_detectable_rate_is_where_the_power_crosses_80_percent():
    level = PowerSettings().level
    p = rate_mde(10, 0.0, level)
    assert p is not None and exact_rate_power(10, p, 0.0, level) >= 0.8 > exact_rate_power(10, p - 0.01, 0.0, level)
    assert rate_mde(10, 0.5, level) is None  # 10 episodes cannot show 0.5 -> anything at 80 %


def test_cli_writes_curves_and_states_the_minimal_effects(tmp_path, capsys):
    out = tmp_path / "power"
    assert main(["power", "--sims", "20", "--set", "shipped", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Minimal detectable effects at 80 % power" in text and "| door | 10 |" in text
    data = json.loads((out / "power.json").read_text())
    assert data["groups"] == {"door": 10, "pick_place": 12, "all": 22}
    assert data["words"]["difference"] == pytest.approx(10.25)
    png = (out / "power_curves.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_the_extended_set_is_analysed_beside_the_shipped_one_and_detects_60_vs_30(tmp_path, capsys):
    from vlmproprio.power import set_groups

    assert set_groups("extended") == {
        "extended/door": 60,
        "extended/pick_place": 96,
        "extended/stack": 60,
        "extended/all": 216,
    }
    out = tmp_path / "power"
    assert main(["power", "--sims", "20", "--out", str(out)]) == 0  # default: both sets
    text = capsys.readouterr().out
    assert "| door | 10 |" in text and "| extended/all | 216 |" in text
    data = json.loads((out / "power.json").read_text())
    correct = data["correctness"]
    assert (correct["p"], correct["q"]) == (0.6, 0.3)
    assert correct["power"]["extended/all"] >= 0.8 > correct["power"]["all"]  # the target, and why
    assert correct["episodes_needed"] > 22
    assert main(["power", "--set", "nope", "--out", str(out)]) == 2
    assert "unknown episode set 'nope'" in capsys.readouterr().err


def test_the_test_above_62_episodes_draws_the_patterns_stats_draws():
    """Over 62 episodes a pattern is n coin flips, not one integer's bits: the simulation's p-values must still
    be the suite's own, one by one."""
    import numpy as np

    from vlmproprio.power import sign_flip_p_many
    from vlmproprio.stats import sign_flip_p

    d = np.random.default_rng(3).normal(0.1, 1.0, size=(4, 216))
    assert sign_flip_p_many(d).tolist() == [sign_flip_p(row)[0] for row in d]


def test_cli_refuses_bad_settings_in_one_line(tmp_path, capsys):
    assert main(["power", "--alpha", "1.5", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "alpha" in err[0]
    with pytest.raises(Exception, match="probabilities"):
        analyse(PowerSettings(n_sims=10), correctness=(1.2, 0.0))


def test_default_family_is_the_pre_registered_primary_family():
    """Power is computed at the level the verdicts use: alpha / the number of primary hypotheses in claims.yml."""
    import yaml

    from vlmproprio import power
    from vlmproprio.verdicts import CLAIMS_FILE

    claims = yaml.safe_load(CLAIMS_FILE.read_text())
    assert power.PowerSettings().family == len(claims["primary"])
    assert power.PowerSettings().alpha == claims["alpha"]


# ---------------------------------------------------------------------------------------------- the report's cache

SMALL = {"door": 3, "all": 5}


def _small_settings(**kw):
    from vlmproprio.power import PowerSettings

    return PowerSettings(n_sims=20, **kw)


def test_a_cached_analysis_is_the_analysis_bit_for_bit(tmp_path, monkeypatch):
    import vlmproprio.power as P

    fresh = P.analyse(_small_settings(), groups=SMALL)
    first = P.analyse_cached(_small_settings(), SMALL, tmp_path / "power")
    assert first == fresh
    monkeypatch.setattr(P, "analyse", lambda *a, **k: pytest.fail("computed again"))
    again = P.analyse_cached(_small_settings(), SMALL, tmp_path / "power")
    assert again == fresh and json.dumps(again.to_dict()) == json.dumps(fresh.to_dict())
    assert isinstance(again.shift_curves["door"][0], tuple)  # as analyse gives them


def test_other_settings_or_episodes_are_computed_not_read(tmp_path, monkeypatch):
    import vlmproprio.power as P

    P.analyse_cached(_small_settings(), SMALL, tmp_path / "power")
    calls = []
    real = P.analyse
    monkeypatch.setattr(P, "analyse", lambda *a, **k: calls.append(1) or real(*a, **k))
    other = P.analyse_cached(_small_settings(alpha=0.01), SMALL, tmp_path / "power")
    assert other.settings["alpha"] == 0.01
    P.analyse_cached(_small_settings(), {"door": 4, "all": 5}, tmp_path / "power")
    assert len(calls) == 2
    assert P.analysis_key(_small_settings(), SMALL) != P.analysis_key(_small_settings(seed=1), SMALL)


def test_a_damaged_or_unusable_cache_only_means_computing(tmp_path):
    import vlmproprio.power as P
    from vlmproprio.stores import JSON_VALUES, open_store

    fresh = P.analyse(_small_settings(), groups=SMALL)
    with open_store(tmp_path / "power", JSON_VALUES, error=RuntimeError, what="test") as store:
        store[P.analysis_key(_small_settings(), SMALL)] = {"rate_curves": 3}
    assert P.analyse_cached(_small_settings(), SMALL, tmp_path / "power") == fresh
    with open_store(tmp_path / "power", JSON_VALUES, error=RuntimeError, what="test") as store:
        assert store[P.analysis_key(_small_settings(), SMALL)] == json.loads(json.dumps(fresh.to_dict()))
    blocker = tmp_path / "file"
    blocker.write_text("in the way")
    assert P.analyse_cached(_small_settings(), SMALL, blocker) == fresh


def test_damaged_bytes_in_the_cache_only_mean_computing(tmp_path):
    import sqlite3

    import vlmproprio.power as P

    fresh = P.analyse_cached(_small_settings(), SMALL, tmp_path / "power")
    with sqlite3.connect(tmp_path / "power" / "cache.db") as db:
        assert db.execute("UPDATE Cache SET value = X'DEADBEEF'").rowcount == 1  # not zlib, not JSON
    assert P.analyse_cached(_small_settings(), SMALL, tmp_path / "power") == fresh
