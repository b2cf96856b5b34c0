"""Episodes: the frozen robot recordings every later stage reads.

On disk an episode is a folder ``<root>/episodes/<episode_id>/``::

    episode.json    metadata, one row per sampled frame (step, state, ground truth)
    steps.npz       full-rate state and ground truth at every sim step (deflated, no pickle)
    frames/000.png  256x256 RGB, lossless, right side up, one per sampled frame

and ``<root>/manifest.json`` holds the sha256 of every file under ``<root>``.
Loading an episode verifies its files against the manifest, so a changed,
missing or extra file is an error that names it.

State conventions (also written into every episode.json):

* ``joints``: the 7 Panda joint angles in rad, then the gripper opening in m
  (distance between the two finger joints, ~0 closed, ~0.08 fully open).
* ``ee``: x, y, z of the grip site in m in the world frame, then roll, pitch,
  yaw in rad: extrinsic x-y-z Euler angles of ``robot0_eef_quat``, unwrapped
  along the episode (``numpy.unwrap``), so they may leave (-pi, pi] but never jump.
* directions are in the robot's frame: forward = +x (away from the base),
  left = +y, up = +z.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import zipfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from vlmproprio.digests import file_signature, settled
from vlmproprio.errors import VlmproprioError

# atomic_write_* and sha256_file live in vlmproprio.io; importing them from here keeps working
from vlmproprio.io import JSONLoadError, atomic_write_bytes, atomic_write_text, load_json, sha256_file

FORMAT_VERSION = 1
TASKS = ("door", "pick_place", "lift")
JOINT_DIM = 8
EE_DIM = 6
MANIFEST_NAME = "manifest.json"
EPISODE_FILE = "episode.json"
STEPS_FILE = "steps.npz"
FRAMES_DIR = "frames"

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the empty IEND chunk and its CRC: every complete PNG ends so

# Episode ids become path components: keep them to a closed alphabet so that no id can leave its folder.
EPISODE_ID_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")

STATE_CONVENTIONS = {
    "joints": "7 joint angles (rad) then gripper opening (m, distance between the finger joints)",
    "ee": "x, y, z of the grip site (m, world frame) then roll, pitch, yaw (rad, extrinsic xyz Euler "
    "of robot0_eef_quat, unwrapped along the episode)",
    "directions": "robot frame: forward=+x (away from the base), left=+y, up=+z",
}


class EpisodeError(VlmproprioError):
    """An episode or fixture set that cannot be used; the message names the file and what is wrong."""


# (sha256 of a PNG file's bytes + the pixel digest it must have) already checked in this process, or by an
# earlier one that recorded it in a pixel ledger (see pixel_ledger)
_PIXELS_VERIFIED: set[bytes] = set()
PIXEL_LEDGER_FILE = "verified-pixels.txt"
_LEDGER_LINE = re.compile(r"^([0-9a-f]{64}) ([0-9a-f]{64})$")
MAX_LEDGER_BYTES = 8 * 1024 * 1024  # ~60 000 frames; a larger file is ignored (and rewritten smaller)


@dataclass(frozen=True)
class Frame:
    """One sampled frame: the image, the robot state at that moment and its ground truth."""

    index: int
    step: int
    image_path: Path
    image_sha256: str
    joints: tuple[float, ...]
    ee: tuple[float, ...]
    phase: str
    direction: str

    def image_bytes(self) -> bytes:
        """The PNG file as it is (what a model is sent); EpisodeError when it is not a whole PNG or its
        decoded pixels do not hash to the episode's ``pixel_sha256`` for this frame.

        The pixel check decodes the image (~2-3 ms per 256x256 frame on this project's CPU), once per file
        content and process: a flipped pixel or two swapped frames are caught even after the manifest was
        regenerated, and scoring, which sends no image, pays nothing."""
        try:
            data = self.image_path.read_bytes()
        except OSError as exc:
            raise EpisodeError(f"{self.image_path}: cannot read image ({exc.strerror or exc})") from exc
        if not (data.startswith(PNG_SIGNATURE) and data.endswith(PNG_END)):
            raise EpisodeError(
                f"{self.image_path}: not a complete PNG file (truncated or damaged); restore it (git checkout) "
                "or re-record the episode"
            )
        self._check_pixels(data)
        return data

    def _check_pixels(self, data: bytes) -> None:
        seen = hashlib.sha256(data).digest() + self.image_sha256.encode()
        if seen in _PIXELS_VERIFIED:
            return
        from PIL import Image

        try:
            with Image.open(io.BytesIO(data)) as im:
                rgb = np.asarray(im.convert("RGB"))
        except (OSError, SyntaxError, ValueError) as exc:
            raise EpisodeError(f"{self.image_path}: cannot decode image ({exc})") from exc
        if pixel_sha256(rgb) != self.image_sha256:
            raise EpisodeError(
                f"{self.image_path}: its pixels differ from frame {self.index}'s pixel_sha256 in "
                f"{self.image_path.parent.parent / EPISODE_FILE} (image changed, damaged or swapped with another "
                "frame); restore it (git checkout) or re-record the episode"
            )
        _PIXELS_VERIFIED.add(seen)

    def image_array(self) -> np.ndarray:
        """Decoded RGB pixels (H, W, 3) uint8."""
        from PIL import Image

        try:
            with Image.open(self.image_path) as im:
                im.load()
                return np.asarray(im.convert("RGB"))
        except (OSError, SyntaxError, ValueError) as exc:
            raise EpisodeError(f"{self.image_path}: cannot decode image ({exc})") from exc


IMAGE_THREADS = 4  # a cold pixel check is PNG decoding, which Pillow does without holding the GIL


def frame_images(frames: Sequence[Frame]) -> list[bytes]:
    """``[f.image_bytes() for f in frames]``, read and checked by a few threads.

    A process without a pixel ledger decodes every frame (~2 ms each, 1.3 s for the fixtures); the decoding and
    hashing release the GIL, so on two cores this takes about half as long. Same bytes, same order; when frames
    fail, the first failing one in order raises, as the plain loop would."""
    if len(frames) < 2:
        return [f.image_bytes() for f in frames]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(IMAGE_THREADS, len(frames)), thread_name_prefix="frame-images") as pool:
        return list(pool.map(Frame.image_bytes, frames))


@dataclass(frozen=True)
class TargetBin:
    """Where the object must go in PickPlace, in robosuite's index and in words as seen in the image."""

    index: int
    row: str  # "near" | "far"  (from the robot; near is the bottom row of the image)
    side: str  # "left" | "right" (the robot's and the image's left/right)
    description: str


@dataclass(frozen=True)
class StepStates:
    """Full-rate state and ground truth at every sim step (arrays of length ``steps + 1``)."""

    step: np.ndarray  # (T,) int
    joints: np.ndarray  # (T, 8)
    ee: np.ndarray  # (T, 6)
    phase: np.ndarray  # (T,) int index into Episode.phase_names
    direction: np.ndarray  # (T,) int index into Episode.direction_vocab


@dataclass(frozen=True)
class PhaseSpan:
    name: str
    start_step: int
    end_step: int  # inclusive


@dataclass
class Episode:
    episode_id: str
    root: Path
    task: str
    env_name: str
    target_object: str
    action: str
    instruction: str
    target_bin: TargetBin | None
    seed: int
    steps: int
    stride: int
    camera: str
    image_size: tuple[int, int]
    versions: dict[str, str]
    success: bool
    phase_names: tuple[str, ...]
    direction_vocab: tuple[str, ...]
    phases: tuple[PhaseSpan, ...]
    frames: tuple[Frame, ...]
    extra: dict = field(default_factory=dict)

    @property
    def frame_phases(self) -> list[str]:
        return [f.phase for f in self.frames]

    def boundaries(self) -> list[int]:
        """Ground-truth boundaries between sampled frames: j means a new phase starts at frame j + 1.

        Indexed like the similarity trace (caption j against caption j + 1)."""
        ph = self.frame_phases
        return [j for j in range(len(ph) - 1) if ph[j] != ph[j + 1]]

    @cached_property
    def step_states(self) -> StepStates:
        return read_steps(self.root / STEPS_FILE)

    def joints_array(self) -> np.ndarray:
        return np.array([f.joints for f in self.frames], dtype=np.float64)

    def ee_array(self) -> np.ndarray:
        return np.array([f.ee for f in self.frames], dtype=np.float64)


# ---------------------------------------------------------------------------------------------- ids


def check_episode_id(episode_id: str) -> str:
    if not isinstance(episode_id, str) or not EPISODE_ID_RE.match(episode_id):
        raise EpisodeError(
            f"invalid episode id {episode_id!r}: use lower-case letters, digits, '_' and '-' "
            "(no path separators, no '..')"
        )
    return episode_id


def standard_episode_ids() -> list[str]:
    """The paper's 22: 10 Door episodes and 3 per target bin for PickPlaceCereal."""
    return [f"door_{s:02d}" for s in range(10)] + [f"bin{b}_{s:02d}" for b in range(4) for s in range(3)]


# ---------------------------------------------------------------------------------------------- hashing


def pixel_sha256(rgb: np.ndarray) -> str:
    """Hash of decoded pixels: equal images hash equal whatever PNG encoder wrote them."""
    arr = np.ascontiguousarray(rgb, dtype=np.uint8)
    h = hashlib.sha256(f"{arr.shape}".encode())
    h.update(arr.tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------- manifest


def _fixture_files(root: Path) -> list[str]:
    return sorted(
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.is_file() and p.name != MANIFEST_NAME and not p.name.startswith(".")
    )


def build_manifest(root: Path) -> dict:
    root = Path(root)
    files = {rel: sha256_file(root / rel) for rel in _fixture_files(root)}
    return {"format_version": FORMAT_VERSION, "files": files}


def write_manifest(root: Path) -> Path:
    path = Path(root) / MANIFEST_NAME
    atomic_write_text(path, json.dumps(build_manifest(root), indent=1, sort_keys=True) + "\n")
    return path


def update_manifest(root: Path, rel_paths: Iterable[str]) -> Path:
    """Re-hash only the named files (dropping those that no longer exist).

    Writing a cassette must not bless unrelated changes elsewhere in the fixtures, which rewriting the
    whole manifest would do."""
    root = Path(root)
    files = dict(read_manifest(root))
    for rel in rel_paths:
        path = root / rel
        if path.is_file():
            files[rel] = sha256_file(path)
        else:
            files.pop(rel, None)
    path = root / MANIFEST_NAME
    doc = {"format_version": FORMAT_VERSION, "files": dict(sorted(files.items()))}
    atomic_write_text(path, json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return path


def register_fixture_file(path: Path) -> Path | None:
    """Update the manifest entry of a file written into a fixture set's sub-folder (a cassette in
    ``<fixtures>/responses/``); returns the manifest, or None when the folder above holds no manifest."""
    path = Path(path).resolve()
    root = path.parent.parent
    if not (root / MANIFEST_NAME).is_file():
        return None
    return update_manifest(root, [path.relative_to(root).as_posix()])


def check_fixture_file(path: Path) -> None:
    """A file of a fixture set's sub-folder (a cassette in ``<fixtures>/responses/``) must be the one the
    manifest above it lists: a line edited and re-checksummed is caught before replay uses it. Files outside
    a fixture set (no manifest two levels up) are not checked."""
    path = Path(path).resolve()
    root = path.parent.parent
    if not (root / MANIFEST_NAME).is_file():
        return
    rel = path.relative_to(root).as_posix()
    files = read_manifest(root)
    if rel not in files:
        raise EpisodeError(
            f"{path}: not in {root / MANIFEST_NAME}; a recording registers its cassette there "
            "(`vlmproprio run --model MODEL --mode record` or `vlmproprio cassette export --model MODEL`)"
        )
    if sha256_file(path) != files[rel]:
        raise EpisodeError(
            f"{path}: sha256 differs from {root / MANIFEST_NAME} (changed after it was recorded); restore it "
            f"(`git checkout -- {path}`) or record it again"
        )


def read_manifest(root: Path) -> dict[str, str]:
    path = Path(root) / MANIFEST_NAME
    if not path.is_file():
        raise EpisodeError(
            f"{path}: manifest missing (run `vlmproprio manifest --fixtures {root}` after changing fixtures)"
        )
    try:
        data = load_json(path)
        files = data["files"]
        if not isinstance(files, dict):
            raise TypeError("'files' is not an object")
    except JSONLoadError as exc:
        raise EpisodeError(f"{path}: not a valid manifest ({exc.detail})") from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise EpisodeError(f"{path}: not a valid manifest ({exc})") from exc
    return files


# sha256 of the fixture files hashed in this process, by absolute path, with the stat signature the file had
# (see _file_sha256). A run then a score in one process, or the three loads of a benchmark, hash 50 MB once.
_FILE_DIGESTS: dict[str, tuple[tuple[int, ...], str]] = {}


def _file_sha256(path: Path) -> str:
    """``sha256_file(path)``, hashed again only when the file may have changed since this process hashed it.

    An unchanged signature (vlmproprio.digests.file_signature) means the same bytes; a file that changed just
    before it was hashed is not remembered (digests.settled). Within one process only: the fixtures' bytes are
    checked for corruption under the file system too, which no signature shows."""
    key = os.path.abspath(path)
    sig = file_signature(os.stat(key))
    known = _FILE_DIGESTS.get(key)
    if known is not None and known[0] == sig:
        return known[1]
    digest = sha256_file(key)
    if settled(sig):
        _FILE_DIGESTS[key] = (sig, digest)
    return digest


def verify_files(root: Path, prefix: str = "", manifest: dict[str, str] | None = None) -> int:
    """Check every file under ``root/prefix`` against the manifest; return how many were checked.

    Raises EpisodeError naming the first file that is changed, missing or not in the manifest."""
    if prefix and not prefix.endswith("/"):
        raise ValueError("prefix must end with '/'")
    root = Path(root)
    manifest = read_manifest(root) if manifest is None else manifest
    expected = {k: v for k, v in manifest.items() if k.startswith(prefix)}
    here = root / prefix
    present = {prefix + rel for rel in _fixture_files(here)} if here.is_dir() else set()
    for rel in sorted(present - expected.keys()):
        raise EpisodeError(f"{root / rel}: extra file, not in {root / MANIFEST_NAME}")
    for rel in sorted(expected.keys() - present):
        raise EpisodeError(f"{root / rel}: missing (listed in {root / MANIFEST_NAME})")
    for rel in sorted(expected):
        if _file_sha256(root / rel) != expected[rel]:
            raise EpisodeError(f"{root / rel}: sha256 differs from {root / MANIFEST_NAME} (file changed or corrupt)")
    return len(expected)


# ---------------------------------------------------------------------------------------------- pixel ledger


@contextlib.contextmanager
def pixel_ledger(path: Path | None) -> Iterator[None]:
    """Within the block, a frame whose exact PNG bytes an earlier process decoded and matched to the same pixel
    digest (``path``: a text file in the cache folder, one ``<file sha256> <pixel sha256>`` line per pair) is not
    decoded again; on leaving, the pairs verified so far are written back.

    Decoding every frame costs ~1.3 s per process, the whole pixel check. Skipping it is as safe as the ledger:
    a pair is recorded only after its pixels were decoded and matched here, and any other bytes or digest (a
    flipped pixel, swapped frames, an edited episode.json) is not in it, so it is decoded and checked as before.
    A missing, unreadable or damaged ledger just means decoding; one that cannot be written is left as it is."""
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


# ---------------------------------------------------------------------------------------------- io helpers


def write_steps(path: Path, states: StepStates) -> None:
    """A deterministic .npz: fixed member order and timestamps, so equal arrays give equal bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name in ("step", "joints", "ee", "phase", "direction"):
            arr = np.ascontiguousarray(getattr(states, name))
            member = io.BytesIO()
            np.save(member, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue(), compresslevel=9)
    atomic_write_bytes(path, buf.getvalue())


def read_steps(path: Path) -> StepStates:
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("step", "joints", "ee", "phase", "direction")}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise EpisodeError(f"{path}: cannot read full-rate states ({exc})") from exc
    n = len(arrays["step"])
    shapes = {"joints": (n, JOINT_DIM), "ee": (n, EE_DIM), "phase": (n,), "direction": (n,)}
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise EpisodeError(f"{path}: {k} has shape {arrays[k].shape}, expected {shape}")
    if not (np.isfinite(arrays["joints"]).all() and np.isfinite(arrays["ee"]).all()):
        raise EpisodeError(f"{path}: non-finite values in the full-rate states")
    return StepStates(**arrays)


# ---------------------------------------------------------------------------------------------- load


def _vector(value, dim: int, what: str, where: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != dim:
        raise EpisodeError(f"{where}: {what} must be a list of {dim} numbers, got {value!r:.80}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise EpisodeError(f"{where}: {what} has a non-finite or non-numeric value {v!r}")
        out.append(float(v))
    return tuple(out)


def _parse_episode(episode_dir: Path, data: dict) -> Episode:
    where = str(episode_dir / EPISODE_FILE)
    try:
        if data.get("format_version") != FORMAT_VERSION:
            raise EpisodeError(f"{where}: format_version {data.get('format_version')!r}, expected {FORMAT_VERSION}")
        if data["task"] not in TASKS:
            raise EpisodeError(f"{where}: unknown task {data['task']!r} (known: {', '.join(TASKS)})")
        frames = []
        inside = episode_dir.resolve()  # once per episode, not per frame
        for i, row in enumerate(data["frames"]):
            fw = f"{where}: frames[{i}]"
            if row["index"] != i:
                raise EpisodeError(f"{fw}: index {row['index']} out of order")
            img = episode_dir / row["file"]
            if inside not in img.resolve().parents:
                raise EpisodeError(f"{fw}: image path {row['file']!r} leaves the episode folder")
            frames.append(
                Frame(
                    index=i,
                    step=int(row["step"]),
                    image_path=img,
                    image_sha256=str(row["pixel_sha256"]),
                    joints=_vector(row["joints"], JOINT_DIM, "joints", fw),
                    ee=_vector(row["ee"], EE_DIM, "ee", fw),
                    phase=str(row["phase"]),
                    direction=str(row["direction"]),
                )
            )
        if not frames:
            raise EpisodeError(f"{where}: no frames")
        tb = data.get("target_bin")
        target_bin = TargetBin(**tb) if tb else None
        return Episode(
            episode_id=check_episode_id(data["episode_id"]),
            root=episode_dir,
            task=data["task"],
            env_name=data["env_name"],
            target_object=data["target_object"],
            action=data["action"],
            instruction=data["instruction"],
            target_bin=target_bin,
            seed=int(data["seed"]),
            steps=int(data["steps"]),
            stride=int(data["stride"]),
            camera=data["camera"],
            image_size=tuple(data["image_size"]),
            versions=dict(data["versions"]),
            success=bool(data["success"]),
            phase_names=tuple(data["phase_names"]),
            direction_vocab=tuple(data["direction_vocab"]),
            phases=tuple(PhaseSpan(**p) for p in data["phases"]),
            frames=tuple(frames),
            extra=dict(data.get("extra", {})),
        )
    except EpisodeError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise EpisodeError(f"{where}: malformed episode metadata ({type(exc).__name__}: {exc})") from exc


def load_episode(root: Path, episode_id: str, *, verify: bool = True, manifest: dict | None = None) -> Episode:
    """Load ``root/episodes/<episode_id>``, verifying its files against ``root/manifest.json``."""
    root = Path(root)
    check_episode_id(episode_id)
    episode_dir = root / "episodes" / episode_id
    if not episode_dir.is_dir():
        known = ", ".join(list_episode_ids(root)) or "none"
        raise EpisodeError(f"{episode_dir}: no such episode (episodes in {root}: {known})")
    if verify:
        verify_files(root, f"episodes/{episode_id}/", manifest)
    path = episode_dir / EPISODE_FILE
    try:
        data = load_json(path)
    except FileNotFoundError as exc:
        raise EpisodeError(f"{path}: cannot read episode metadata (missing)") from exc
    except JSONLoadError as exc:
        raise EpisodeError(f"{path}: cannot read episode metadata ({exc.detail})") from exc
    if not isinstance(data, dict):
        raise EpisodeError(f"{path}: episode metadata must be a JSON object")
    episode = _parse_episode(episode_dir, data)
    if episode.episode_id != episode_id:
        raise EpisodeError(f"{path}: episode_id {episode.episode_id!r} does not match its folder {episode_id!r}")
    if verify:
        check_steps(episode)
    return episode


def check_steps(episode: Episode) -> None:
    """steps.npz must agree with episode.json: one row per sim step, and at each sampled frame's step the
    same joints, end-effector pose and phase. Reading and comparing costs ~3 ms per episode."""
    path = episode.root / STEPS_FILE
    if not path.is_file():  # an episode without full-rate states (the manifest says whether one is missing)
        return
    states = episode.step_states
    n = len(states.step)
    if n != episode.steps + 1 or not np.array_equal(states.step, np.arange(n)):
        raise EpisodeError(f"{path}: {n} steps numbered {states.step[:1]}.., expected 0..{episode.steps}")
    for f in episode.frames:
        s = f.step
        ok = 0 <= s < n and np.array_equal(states.joints[s], f.joints) and np.array_equal(states.ee[s], f.ee)
        if ok:
            p = int(states.phase[s])
            ok = 0 <= p < len(episode.phase_names) and episode.phase_names[p] == f.phase
        if not ok:
            raise EpisodeError(
                f"{path}: step {s} disagrees with frame {f.index} of {episode.root / EPISODE_FILE} (states or "
                "phase differ: the file was changed or belongs to another episode); restore it or re-record"
            )


def list_episode_ids(root: Path) -> list[str]:
    d = Path(root) / "episodes"
    if not d.is_dir():
        return []
    return sorted(p.name for p in d.iterdir() if p.is_dir() and EPISODE_ID_RE.match(p.name))


def load_episodes(root: Path, episode_ids: Sequence[str] | None = None, *, verify: bool = True) -> list[Episode]:
    root = Path(root)
    manifest = read_manifest(root) if verify else None
    if verify:
        # an extra episode folder is an error too, not something to skip silently
        listed = {k.split("/")[1] for k in manifest if k.startswith("episodes/")}
        for eid in list_episode_ids(root):
            if eid not in listed:
                raise EpisodeError(f"{root / 'episodes' / eid}: extra episode, not in {root / MANIFEST_NAME}")
    ids = list(episode_ids) if episode_ids is not None else list_episode_ids(root)
    if not ids:
        raise EpisodeError(f"{root / 'episodes'}: no episodes found")
    return [load_episode(root, eid, verify=verify, manifest=manifest) for eid in ids]


# ---------------------------------------------------------------------------------------------- save


def episode_metadata(
    *,
    episode_id: str,
    task: str,
    env_name: str,
    target_object: str,
    action: str,
    instruction: str,
    target_bin: TargetBin | None,
    seed: int,
    steps: int,
    stride: int,
    camera: str,
    image_size: tuple[int, int],
    versions: dict[str, str],
    success: bool,
    phase_names: Sequence[str],
    direction_vocab: Sequence[str],
    phases: Iterable[PhaseSpan],
    frame_rows: list[dict],
    extra: dict | None = None,
) -> dict:
    return {
        "format_version": FORMAT_VERSION,
        "episode_id": check_episode_id(episode_id),
        "task": task,
        "env_name": env_name,
        "target_object": target_object,
        "action": action,
        "instruction": instruction,
        "target_bin": None if target_bin is None else target_bin.__dict__,
        "seed": seed,
        "steps": steps,
        "stride": stride,
        "camera": camera,
        "image_size": list(image_size),
        "versions": versions,
        "success": success,
        "state_conventions": STATE_CONVENTIONS,
        "phase_names": list(phase_names),
        "direction_vocab": list(direction_vocab),
        "phases": [p.__dict__ for p in phases],
        "frames": frame_rows,
        "extra": extra or {},
    }


def write_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), "RGB").save(buf, format="PNG", optimize=True)
    atomic_write_bytes(path, buf.getvalue())


def write_episode(root: Path, metadata: dict, images: Sequence[np.ndarray], states: StepStates) -> Path:
    """Write one episode folder (replacing any old one). The caller rewrites the manifest afterwards."""
    import shutil

    episode_dir = Path(root) / "episodes" / check_episode_id(metadata["episode_id"])
    if episode_dir.exists():
        shutil.rmtree(episode_dir)
    (episode_dir / FRAMES_DIR).mkdir(parents=True)
    if len(images) != len(metadata["frames"]):
        raise ValueError(f"{len(images)} images for {len(metadata['frames'])} frame rows")
    for row, rgb in zip(metadata["frames"], images, strict=True):
        write_png(episode_dir / row["file"], rgb)
    write_steps(episode_dir / STEPS_FILE, states)
    atomic_write_text(episode_dir / EPISODE_FILE, json.dumps(metadata, indent=1) + "\n")
    return episode_dir
