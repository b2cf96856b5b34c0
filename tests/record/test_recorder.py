"""Regenerability: re-recording an episode reproduces the frozen fixture.

episode.json holds every sampled frame's pixel hash, state and ground truth. Ground truth and every non-float
field must be equal exactly. PNG bytes may differ across PNG encoder versions, so frames are compared through
their decoded pixels (the fresh frames are written as cheap level-1 PNGs, see tests/png_helpers.py).

What depends on the CPU is bounded, not waived. The simulated states may differ in their last bits on a CPU
with other vector instructions than the recording machine's (AVX2 vs AVX-512 change MuJoCo's and numpy's float
order): they are compared to 1e-9 relative. The software rasteriser (Mesa's llvmpipe) compiles its shaders for
the CPU it runs on, so on another CPU a frame's pixels may differ by rounding: every frame must then hash to
the fixture's, or differ from it by at most PIXEL_ATOL in at most PIXEL_SHARE of its values (seen on an Intel
Xeon against fixtures rendered on an AMD EPYC: 1 or 2 levels in 1.2 % of the values). A different scene, pose
or camera changes far more than that, and nothing a caption or a phase boundary can see.
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

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


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
    assert len(fresh.frames) == len(frozen.frames)
    for new, old in zip(fresh.frames, frozen.frames, strict=True):
        new.image_bytes()  # a whole PNG whose decoded pixels hash to the episode's own pixel_sha256
        if new.image_sha256 != old.image_sha256:
            _assert_pixels_close(new.image_path, old.image_path)
    _assert_close(
        _without_pixel_hashes(json.loads((fresh.root / "episode.json").read_text())),
        _without_pixel_hashes(json.loads((frozen.root / "episode.json").read_text())),
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
PIXEL_ATOL, PIXEL_SHARE = 3, 0.05


def _assert_pixels_close(fresh: Path, frozen: Path) -> None:
    """The rasteriser's rounding on another CPU (module docstring), and nothing more."""
    from PIL import Image

    x = np.asarray(Image.open(fresh).convert("RGB"), dtype=np.int16)
    y = np.asarray(Image.open(frozen).convert("RGB"), dtype=np.int16)
    assert x.shape == y.shape, (fresh.name, x.shape, y.shape)
    diff = np.abs(x - y)
    share = float((diff > 0).mean())
    assert int(diff.max()) <= PIXEL_ATOL and share <= PIXEL_SHARE, (fresh.name, int(diff.max()), share)


def _without_pixel_hashes(episode: dict) -> dict:
    return episode | {"frames": [{k: v for k, v in f.items() if k != "pixel_sha256"} for f in episode["frames"]]}


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


def test_the_pixel_tolerance_takes_rounding_and_rejects_a_moved_scene(tmp_path: Path) -> None:
    from PIL import Image

    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    rounded = base.copy()
    rounded[0, :8] = np.clip(rounded[0, :8].astype(int) + 2, 0, 255).astype(np.uint8)
    paths = {}
    for name, img in {"base": base, "rounded": rounded, "moved": np.roll(base, 1, axis=1)}.items():
        paths[name] = tmp_path / f"{name}.png"
        Image.fromarray(img).save(paths[name])
    _assert_pixels_close(paths["rounded"], paths["base"])
    with pytest.raises(AssertionError):
        _assert_pixels_close(paths["moved"], paths["base"])
