"""Frame images: the PNG files, the digest of their decoded pixels, and which files this process (or an
earlier one, through a pixel ledger) has already matched to their digest.

A frame's file is checked twice over: its bytes against the manifest (``manifest.verify_files``) and its
decoded pixels against the episode's ``pixel_sha256``, which catches a flipped pixel or two swapped frames
even after the manifest was regenerated.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from vlmproprio.episodes.types import EPISODE_FILE, EpisodeError
from vlmproprio.errors import VlmproprioError
from vlmproprio.io import ReadError, atomic_write_bytes, read_limited

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the empty IEND chunk and its CRC: every complete PNG ends so

# (sha256 of a PNG file's bytes + the pixel digest it must have) already checked in this process, or by an
# earlier one that recorded it in a pixel ledger (see pixel_ledger)
_PIXELS_VERIFIED: set[bytes] = set()
PIXEL_LEDGER_FILE = "verified-pixels.txt"
_LEDGER_LINE = re.compile(r"^([0-9a-f]{64}) ([0-9a-f]{64})$")
MAX_LEDGER_BYTES = 8 * 1024 * 1024  # ~60 000 frames; a larger file is ignored (and rewritten smaller)


def pixel_sha256(rgb: np.ndarray) -> str:
    """Hash of decoded pixels: equal images hash equal whatever PNG encoder wrote them."""
    arr = np.ascontiguousarray(rgb, dtype=np.uint8)
    h = hashlib.sha256(f"{arr.shape}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()


def read_checked_png(path: Path, digest: str, index: int) -> bytes:
    """The PNG file as it is (what a model is sent); EpisodeError when it is not a whole PNG or its decoded
    pixels do not hash to ``digest``, the ``pixel_sha256`` of frame ``index``.

    The pixel check decodes the image, once per file content and process: scoring, which sends no image,
    pays nothing."""
    data = read_image_file(path)
    if not (data.startswith(PNG_SIGNATURE) and data.endswith(PNG_END)):
        raise EpisodeError(
            f"{path}: not a complete PNG file (truncated or damaged); restore it (git checkout) "
            "or re-record the episode"
        )
    _check_pixels(path, data, digest, index)
    return data


def _check_pixels(path: Path, data: bytes, digest: str, index: int) -> None:
    seen = hashlib.sha256(data).digest() + digest.encode()
    if seen in _PIXELS_VERIFIED:
        return

    rgb = decode_png_bytes(path, data)
    if pixel_sha256(rgb) != digest:
        raise EpisodeError(
            f"{path}: its pixels differ from frame {index}'s pixel_sha256 in "
            f"{path.parent.parent / EPISODE_FILE} (image changed, damaged or swapped with another "
            "frame); restore it (git checkout) or re-record the episode"
        )
    _PIXELS_VERIFIED.add(seen)


def read_image_file(path: Path) -> bytes:
    """The bytes of an image file, read with ``vlmproprio.io.read_limited`` (a regular file, bounded)."""
    try:
        return read_limited(path)
    except FileNotFoundError as exc:
        raise EpisodeError(f"{path}: cannot read image (missing)") from exc
    except ReadError as exc:
        raise EpisodeError(f"{path}: cannot read image ({exc.detail})") from exc


def decode_png_bytes(path: Path, data: bytes) -> np.ndarray:
    """Decoded RGB pixels (H, W, 3) uint8 of the image file ``path`` whose bytes are ``data``; EpisodeError
    naming it when they do not decode, or would decode to more pixels than PIL allows (a decompression bomb:
    a few KB of PNG claiming 16000 x 16000 pixels)."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except Image.DecompressionBombError as exc:
        raise EpisodeError(f"{path}: image too large to decode ({exc})") from exc
    except (OSError, SyntaxError, ValueError, EOFError) as exc:
        raise EpisodeError(f"{path}: cannot decode image ({exc})") from exc


def decode_rgb(path: Path) -> np.ndarray:
    """Decoded RGB pixels (H, W, 3) uint8."""
    return decode_png_bytes(path, read_image_file(path))


def write_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(buf, format="PNG", optimize=True)
    atomic_write_bytes(path, buf.getvalue())


@contextlib.contextmanager
def pixel_ledger(path: Path | None) -> Iterator[None]:
    """Within the block, a frame whose exact PNG bytes an earlier process decoded and matched to the same pixel
    digest (``path``: a text file in the cache folder, one ``<file sha256> <pixel sha256>`` line per pair) is not
    decoded again; on leaving, the pairs verified so far are written back.

    Skipping the decode is as safe as the ledger: a pair is recorded only after its pixels were decoded and
    matched here, and any other bytes or digest (a flipped pixel, swapped frames, an edited episode.json) is not
    in it, so it is decoded and checked. A missing, unreadable or damaged ledger just means decoding; one that
    cannot be written is left as it is."""
    if path is None:
        yield
        return
    known = _read_pixel_ledger(path)
    _PIXELS_VERIFIED.update(known)
    try:
        yield
    finally:
        if _PIXELS_VERIFIED - known:  # new pairs were verified
            _write_pixel_ledger(path, _PIXELS_VERIFIED)


def _read_pixel_ledger(path: Path) -> set[bytes]:
    try:
        if path.stat().st_size > MAX_LEDGER_BYTES:
            return set()
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError):
        return set()
    pairs = (_LEDGER_LINE.match(line) for line in text.splitlines())
    return {bytes.fromhex(m[1]) + m[2].encode() for m in pairs if m}


def _write_pixel_ledger(path: Path, verified: set[bytes]) -> None:
    lines = sorted(f"{key[:32].hex()} {key[32:].decode()}" for key in verified if len(key) == 96)
    # a read-only or full cache folder: the next process decodes again, nothing is lost
    with contextlib.suppress(VlmproprioError, OSError, UnicodeError):
        atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("ascii"))
