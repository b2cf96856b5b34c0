"""Regenerability: re-recording an episode reproduces the frozen fixture exactly.

episode.json holds every sampled frame's pixel hash, state and ground truth, so equal episode.json and
steps.npz bytes mean equal pixels, states and phases (PNG bytes may differ across PNG encoder versions and
are therefore compared through their decoded pixels).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from vlmproprio.episodes import load_episode, sha256_file

pytest.importorskip(
    "robosuite",
    reason="re-recording needs the [record] extra (robosuite==1.5.2, mujoco==3.3.7); "
    "install it with `pip install -e .[record]` to check that the fixtures can be regenerated",
)

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.mark.record
@pytest.mark.slow
@pytest.mark.parametrize("episode_id", ["door_03", "bin3_00"])
def test_rerecording_reproduces_the_fixture(tmp_path: Path, episode_id: str) -> None:
    from vlmproprio.record.recorder import episode_spec, record_episode

    frozen = load_episode(FIXTURES, episode_id)
    record_episode(episode_spec(episode_id), tmp_path)
    fresh = load_episode(tmp_path, episode_id, verify=False)
    assert [f.image_sha256 for f in fresh.frames] == [f.image_sha256 for f in frozen.frames]
    assert [f.joints + f.ee for f in fresh.frames] == [f.joints + f.ee for f in frozen.frames]
    for name in ("episode.json", "steps.npz"):
        assert sha256_file(fresh.root / name) == sha256_file(frozen.root / name), name
