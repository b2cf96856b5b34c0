"""Cheaper PNG files for the tests that re-run the recorder or the demo importer.

``episodes.pixels.write_png`` saves with ``optimize=True`` (zlib level 9 and a filter search): ~110 ms per 256x256
frame on this project's CPU, a fifth of a re-recording's CPU time. The tests that use ``fast_png_writes``
compare frames through their decoded pixels (``pixel_sha256``), never through PNG bytes, which may differ
across encoders anyway; a level-1 PNG (~7 ms) is just as lossless, so they check the same. The real encoder
keeps its own coverage: tests/episodes write episodes with it, and the frozen fixtures were written by it.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from vlmproprio.episodes import pixels
from vlmproprio.io import atomic_write_bytes


def write_png_level1(path: Path, rgb: np.ndarray) -> None:
    """``episodes.pixels.write_png`` with zlib level 1 instead of level 9 plus a filter search: the same pixels."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(buf, format="PNG", compress_level=1)
    atomic_write_bytes(path, buf.getvalue())


@contextmanager
def fast_png_writes() -> Iterator[None]:
    """Episodes written inside the block (``episodes.write_episode``) get level-1 PNG frames."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pixels, "write_png", write_png_level1)
        yield
