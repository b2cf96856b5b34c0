"""Episode ids: a closed alphabet that cannot leave its folder, and the paper's 22."""

from __future__ import annotations

from pathlib import Path

import pytest

from vlmproprio import episodes as E


@pytest.mark.parametrize("bad", ["../door_00", "door/00", "..", "", "Door 00", "a" * 80])
def test_episode_ids_cannot_leave_their_folder(fixture_root: Path, bad: str) -> None:
    with pytest.raises(E.EpisodeError, match="invalid episode id"):
        E.load_episode(fixture_root, bad)


def test_standard_ids() -> None:
    ids = E.standard_episode_ids()
    assert len(ids) == 22 and ids[0] == "door_00" and ids[-1] == "bin3_02"
