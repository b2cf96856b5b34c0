"""Frame images: a damaged PNG is a clear error, and the pixel ledger skips decoding only bytes verified before."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vlmproprio import episodes as E
from vlmproprio.episodes import pixels

from .support import fresh_process


def test_truncated_png_is_a_clear_error(fixture_root: Path) -> None:
    path = fixture_root / "episodes" / "door_00" / "frames" / "003.png"
    path.write_bytes(path.read_bytes()[:40])
    E.write_manifest(fixture_root)
    ep = E.load_episode(fixture_root, "door_00")
    with pytest.raises(E.EpisodeError, match=r"003\.png: cannot decode image"):
        ep.frames[3].image_array()


def test_the_pixel_ledger_skips_decoding_only_bytes_verified_before(fixture_root: Path, tmp_path, monkeypatch):
    ledger = tmp_path / "cache" / E.PIXEL_LEDGER_FILE
    fresh_process(monkeypatch)
    with E.pixel_ledger(ledger):
        for f in E.load_episode(fixture_root, "door_00").frames:
            f.image_bytes()
    assert len(ledger.read_text().splitlines()) == 4

    # a later process reads the ledger and decodes nothing (a decode would fail here)
    fresh_process(monkeypatch)
    real_digest = pixels.pixel_sha256
    monkeypatch.setattr(pixels, "pixel_sha256", lambda rgb: pytest.fail("decoded a frame the ledger vouches for"))
    with E.pixel_ledger(ledger):
        for f in E.load_episode(fixture_root, "door_00").frames:
            f.image_bytes()
    monkeypatch.setattr(pixels, "pixel_sha256", real_digest)

    # damage behind a regenerated manifest: other bytes or another frame's digest are decoded and caught
    frames = fixture_root / "episodes" / "door_00" / "frames"
    a, b = (frames / "000.png").read_bytes(), (frames / "001.png").read_bytes()
    (frames / "000.png").write_bytes(b)
    (frames / "001.png").write_bytes(a)
    E.write_manifest(fixture_root)
    fresh_process(monkeypatch)
    with E.pixel_ledger(ledger), pytest.raises(E.EpisodeError, match=r"000\.png: its pixels differ"):
        E.load_episode(fixture_root, "door_00").frames[0].image_bytes()
    from PIL import Image

    rgb = np.asarray(Image.open(frames / "001.png").convert("RGB")).copy()
    rgb[3, 3, 0] ^= 1
    Image.fromarray(rgb, "RGB").save(frames / "001.png", format="PNG")
    E.write_manifest(fixture_root)
    fresh_process(monkeypatch)
    with E.pixel_ledger(ledger), pytest.raises(E.EpisodeError, match=r"001\.png: its pixels differ"):
        E.load_episode(fixture_root, "door_00").frames[1].image_bytes()


@pytest.mark.parametrize("damage", ["garbage", "directory in the way"])
def test_a_damaged_or_unwritable_pixel_ledger_only_means_decoding(fixture_root: Path, tmp_path, monkeypatch, damage):
    ledger = tmp_path / E.PIXEL_LEDGER_FILE
    if damage == "garbage":
        ledger.write_bytes(b"\xff\xfe not a ledger\n" + b"ab" * 64 + b"\n")
    else:
        ledger.mkdir()
    fresh_process(monkeypatch)
    with E.pixel_ledger(ledger):
        assert E.load_episode(fixture_root, "door_00").frames[2].image_bytes().startswith(E.PNG_SIGNATURE)
    assert len(pixels._PIXELS_VERIFIED) == 1
    if damage == "garbage":
        assert len(ledger.read_text().splitlines()) == 1  # rewritten with the pair verified
