from __future__ import annotations

from pathlib import Path

import pytest

from .support import synthetic


@pytest.fixture
def fixture_root(tmp_path: Path) -> Path:
    return synthetic(tmp_path / "fx")
