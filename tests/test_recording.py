"""Regenerability: re-recording an episode reproduces the frozen fixture.

episode.json holds every sampled frame's pixel hash, state and ground truth. Pixels, ground truth and every
non-float field must be equal exactly (PNG bytes may differ across PNG encoder versions and are therefore
compared through their decoded pixels; the fresh frames are written as cheap level-1 PNGs, see
tests/png_helpers.py). The simulated states may differ in their last bits on a CPU with other vector
instructions than the recording machine's (AVX2 vs AVX-512 change MuJoCo's and numpy's float order): they are
compared to 1e-9 relative, far below anything a caption or a phase boundary can see.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from vlmproprio.episodes import load_episode

# checked, not imported: every xdist worker collects this module, and only the one that runs it needs robosuite
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("robosuite") is None,
    reason="re-recording needs the [record] extra (robosuite==1.5.2, mujoco==3.3.7); "
    "install it with `pip install -e .[record]` to check that the fixtures can be regenerated",
)

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.mark.record
@pytest.mark.slow
@pytest.mark.parametrize("episode_id", ["door_03", "bin3_00"])
def test_rerecording_reproduces_the_fixture(tmp_path: Path, episode_id: str) -> None:
    from png_helpers import fast_png_writes
    from vlmproprio.record.recorder import episode_spec, record_episode

    frozen = load_episode(FIXTURES, episode_id)
    with fast_png_writes():
        record_episode(episode_spec(episode_id), tmp_path)
    fresh = load_episode(tmp_path, episode_id, verify=False)
    assert [f.image_sha256 for f in fresh.frames] == [f.image_sha256 for f in frozen.frames]
    for frame in fresh.frames:
        frame.image_bytes()  # a whole PNG whose decoded pixels hash to the frame's (= the fixture's) pixel_sha256
    _assert_close(
        json.loads((fresh.root / "episode.json").read_text()),
        json.loads((frozen.root / "episode.json").read_text()),
        "episode.json",
    )
    with np.load(fresh.root / "steps.npz") as a, np.load(frozen.root / "steps.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for name in a.files:
            x, y = a[name], b[name]
            assert x.dtype == y.dtype and x.shape == y.shape, name
            if np.issubdtype(x.dtype, np.floating):
                np.testing.assert_allclose(x, y, rtol=RTOL, atol=ATOL, err_msg=f"steps.npz:{name}")
            else:
                np.testing.assert_array_equal(x, y, err_msg=f"steps.npz:{name}")


RTOL, ATOL = 1e-9, 1e-12


def _assert_close(fresh: object, frozen: object, where: str) -> None:
    """Equal JSON values, floats to RTOL (see the module docstring); ``where`` names the first difference."""
    if isinstance(frozen, float) and isinstance(fresh, int | float):
        assert math.isclose(fresh, frozen, rel_tol=RTOL, abs_tol=ATOL), (where, fresh, frozen)
    elif isinstance(frozen, dict):
        assert isinstance(fresh, dict) and sorted(fresh) == sorted(frozen), where
        for k in frozen:
            _assert_close(fresh[k], frozen[k], f"{where}.{k}")
    elif isinstance(frozen, list):
        assert isinstance(fresh, list) and len(fresh) == len(frozen), where
        for i, (x, y) in enumerate(zip(fresh, frozen, strict=True)):
            _assert_close(x, y, f"{where}[{i}]")
    else:
        assert fresh == frozen, (where, fresh, frozen)
