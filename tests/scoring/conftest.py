"""Shipped fixture episodes for the scoring tests: their expected directions come from their own ground truth
(steps.npz) and their camera pose from lexicons/cameras.json."""

from __future__ import annotations

from pathlib import Path

import pytest

from vlmproprio.episodes import load_episode

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


@pytest.fixture(scope="module")
def ep():
    """Load a fixture episode by id, once per test module."""
    cache = {}

    def get(eid: str):
        if eid not in cache:
            cache[eid] = load_episode(FIXTURES, eid, verify=False)
        return cache[eid]

    return get
