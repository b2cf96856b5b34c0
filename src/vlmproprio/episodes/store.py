"""Episodes on disk: the loaded records (``Episode`` and its ``Frame``s), loading and verifying them, and
writing them.

An episode is a folder ``<root>/episodes/<episode_id>/``::

    episode.json    metadata, one row per sampled frame (step, state, ground truth)
    steps.npz       full-rate state and ground truth at every sim step (deflated, no pickle)
    frames/000.png  256x256 RGB, lossless, right side up, one per sampled frame

Loading an episode verifies its files against the manifest (vlmproprio.episodes.manifest) and steps.npz
against episode.json; a frame's pixels are checked when its image is read (vlmproprio.episodes.pixels).
The state conventions are in vlmproprio.episodes.types.
"""

from __future__ import annotations

import io
import json
import math
import os
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path

import numpy as np

from vlmproprio.episodes import pixels
from vlmproprio.episodes.manifest import check_no_links, read_manifest, verify_files
from vlmproprio.episodes.pixels import decode_rgb, read_checked_png
from vlmproprio.episodes.types import (
    EE_DIM,
    EPISODE_FILE,
    EPISODE_ID_RE,
    FORMAT_VERSION,
    FRAMES_DIR,
    JOINT_DIM,
    MANIFEST_NAME,
    STATE_CONVENTIONS,
    STEPS_FILE,
    TASKS,
    EpisodeError,
    PhaseSpan,
    StepStates,
    TargetBin,
    check_episode_id,
)
from vlmproprio.io import JSONLoadError, ReadError, atomic_write_bytes, atomic_write_text, load_json, read_npz


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
        """The PNG file as it is (what a model is sent), its pixels checked against ``image_sha256``
        (pixels.read_checked_png)."""
        return read_checked_png(self.image_path, self.image_sha256, self.index)

    def image_array(self) -> np.ndarray:
        """Decoded RGB pixels (H, W, 3) uint8."""
        return decode_rgb(self.image_path)


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


IMAGE_THREADS = 4  # a cold pixel check is PNG decoding, which Pillow does without holding the GIL


def frame_images(frames: Sequence[Frame]) -> list[bytes]:
    """``[f.image_bytes() for f in frames]``, read and checked by a few threads.

    A frame no ledger vouches for is decoded, and the decoding and hashing release the GIL, so threads share the
    work across cores. Same bytes, same order; when frames fail, the first failing one in order raises, as the
    plain loop would."""
    if len(frames) < 2:
        return [f.image_bytes() for f in frames]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(IMAGE_THREADS, len(frames)), thread_name_prefix="frame-images") as pool:
        return list(pool.map(Frame.image_bytes, frames))


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


# the arrays of steps.npz and the numpy dtype kinds each may have: integers (i, u) or, for states, floats too
_STEP_KINDS = {"step": "iu", "joints": "iuf", "ee": "iuf", "phase": "iu", "direction": "iu"}


def read_steps(path: Path) -> StepStates:
    try:
        stored = read_npz(path)
    except FileNotFoundError as exc:
        raise EpisodeError(f"{path}: cannot read full-rate states (missing)") from exc
    except ReadError as exc:
        raise EpisodeError(f"{path}: cannot read full-rate states ({exc.detail})") from exc
    missing = [k for k in _STEP_KINDS if k not in stored]
    if missing:
        raise EpisodeError(f"{path}: cannot read full-rate states (no {', '.join(missing)} array)")
    arrays = {k: stored[k] for k in _STEP_KINDS}
    for k, kinds in _STEP_KINDS.items():  # a string or object array would fail later with a Python error
        if arrays[k].dtype.kind not in kinds:
            raise EpisodeError(f"{path}: {k} holds {arrays[k].dtype} values, expected numbers ({kinds})")
    if arrays["step"].ndim != 1:
        raise EpisodeError(f"{path}: step has shape {arrays['step'].shape}, expected one number per step")
    n = len(arrays["step"])
    shapes = {"joints": (n, JOINT_DIM), "ee": (n, EE_DIM), "phase": (n,), "direction": (n,)}
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise EpisodeError(f"{path}: {k} has shape {arrays[k].shape}, expected {shape}")
    if not (np.isfinite(arrays["joints"]).all() and np.isfinite(arrays["ee"]).all()):
        raise EpisodeError(f"{path}: non-finite values in the full-rate states")
    return StepStates(**arrays)


def _vector(value, dim: int, what: str, where: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != dim:
        raise EpisodeError(f"{where}: {what} must be a list of {dim} numbers, got {value!r:.80}")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise EpisodeError(f"{where}: {what} has a non-finite or non-numeric value {v!r}")
        out.append(float(v))
    return tuple(out)


# What each JSON value of episode.json must be (the annotations of TargetBin and PhaseSpan use the same words).
_KINDS = {"str": (str, "a string"), "int": (int, "an integer"), "bool": (bool, "true or false"),
          "dict": (dict, "a JSON object"), "list": (list, "a list")}  # fmt: skip


def _json_kind(value) -> str:
    if value is None:
        return "null"
    names = {
        bool: "true/false",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "an object",
    }
    return f"{names.get(type(value), type(value).__name__)} {json.dumps(value)[:40]}"


def _typed(data: dict, key: str, kind: str, where: str):
    """``data[key]``, which must be of ``kind`` (a key of _KINDS); EpisodeError naming the key and what it holds,
    not a Python error from using it (``TargetBin(**"x")``, ``dict("abc")``)."""
    if key not in data:
        raise EpisodeError(f"{where}: no {key!r}")
    value = data[key]
    types, words = _KINDS[kind]
    if not isinstance(value, types) or (kind == "int" and isinstance(value, bool)):
        raise EpisodeError(f"{where}: {key} must be {words}, got {_json_kind(value)}")
    return value


def _typed_list(data: dict, key: str, item: str, where: str) -> list:
    """``data[key]``: a list whose every element is of kind ``item``."""
    values = _typed(data, key, "list", where)
    types, words = _KINDS[item]
    for i, v in enumerate(values):
        if not isinstance(v, types) or (item == "int" and isinstance(v, bool)):
            raise EpisodeError(f"{where}: {key}[{i}] must be {words}, got {_json_kind(v)}")
    return values


def _record(cls, value, what: str, where: str):
    """The dataclass ``cls`` (TargetBin, PhaseSpan) from a JSON object with exactly its fields, each of its type."""
    names = [f.name for f in fields(cls)]
    if not isinstance(value, dict):
        raise EpisodeError(f"{where}: {what} must be an object with {', '.join(names)}; got {_json_kind(value)}")
    extra = sorted(set(value) - set(names))
    if extra:
        raise EpisodeError(f"{where}: {what} has unknown key(s) {', '.join(map(repr, extra))}")
    return cls(**{f.name: _typed(value, f.name, str(f.type), f"{where}: {what}") for f in fields(cls)})


def _parse_frame(episode_dir: Path, inside: Path, i: int, row, where: str) -> Frame:
    fw = f"{where}: frames[{i}]"
    if not isinstance(row, dict):
        raise EpisodeError(f"{fw} must be an object, got {_json_kind(row)}")
    if _typed(row, "index", "int", fw) != i:
        raise EpisodeError(f"{fw}: index {row['index']} out of order")
    img = episode_dir / _typed(row, "file", "str", fw)
    if "\0" in row["file"] or inside not in img.resolve().parents:
        raise EpisodeError(f"{fw}: image path {row['file']!r} leaves the episode folder")
    return Frame(
        index=i,
        step=_typed(row, "step", "int", fw),
        image_path=img,
        image_sha256=_typed(row, "pixel_sha256", "str", fw),
        joints=_vector(row.get("joints"), JOINT_DIM, "joints", fw),
        ee=_vector(row.get("ee"), EE_DIM, "ee", fw),
        phase=_typed(row, "phase", "str", fw),
        direction=_typed(row, "direction", "str", fw),
    )


def _parse_episode(episode_dir: Path, data: dict) -> Episode:
    where = str(episode_dir / EPISODE_FILE)
    if data.get("format_version") != FORMAT_VERSION:
        raise EpisodeError(f"{where}: format_version {data.get('format_version')!r}, expected {FORMAT_VERSION}")
    task = _typed(data, "task", "str", where)
    if task not in TASKS:
        raise EpisodeError(f"{where}: unknown task {task!r} (known: {', '.join(TASKS)})")
    inside = episode_dir.resolve()  # once per episode, not per frame
    frames = [
        _parse_frame(episode_dir, inside, i, row, where) for i, row in enumerate(_typed(data, "frames", "list", where))
    ]
    if not frames:
        raise EpisodeError(f"{where}: no frames")
    tb = data.get("target_bin")
    image_size = _typed_list(data, "image_size", "int", where)
    if len(image_size) != 2:
        raise EpisodeError(f"{where}: image_size must be [width, height], got {_json_kind(image_size)}")
    extra = data.get("extra", {})
    if not isinstance(extra, dict):
        raise EpisodeError(f"{where}: extra must be a JSON object, got {_json_kind(extra)}")
    phases = _typed(data, "phases", "list", where)
    return Episode(
        episode_id=check_episode_id(_typed(data, "episode_id", "str", where)),
        root=episode_dir,
        task=task,
        env_name=_typed(data, "env_name", "str", where),
        target_object=_typed(data, "target_object", "str", where),
        action=_typed(data, "action", "str", where),
        instruction=_typed(data, "instruction", "str", where),
        target_bin=_record(TargetBin, tb, "target_bin", where) if tb is not None else None,
        seed=_typed(data, "seed", "int", where),
        steps=_typed(data, "steps", "int", where),
        stride=_typed(data, "stride", "int", where),
        camera=_typed(data, "camera", "str", where),
        image_size=tuple(image_size),
        versions=dict(_typed(data, "versions", "dict", where)),
        success=_typed(data, "success", "bool", where),
        phase_names=tuple(_typed_list(data, "phase_names", "str", where)),
        direction_vocab=tuple(_typed_list(data, "direction_vocab", "str", where)),
        phases=tuple(_record(PhaseSpan, p, f"phases[{i}]", where) for i, p in enumerate(phases)),
        frames=tuple(frames),
        extra=dict(extra),
    )


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
    same joints, end-effector pose and phase."""
    path = episode.root / STEPS_FILE
    if not os.path.lexists(path):  # an episode without full-rate states (the manifest says whether one is missing);
        return  # anything else by that name (a folder, a FIFO) is read, and refused by read_npz
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
            check_no_links(root, root / "episodes" / eid)  # the rule manifest and verify apply
            if eid not in listed:
                raise EpisodeError(f"{root / 'episodes' / eid}: extra episode, not in {root / MANIFEST_NAME}")
    ids = list(episode_ids) if episode_ids is not None else list_episode_ids(root)
    if not ids:
        raise EpisodeError(f"{root / 'episodes'}: no episodes found")
    return [load_episode(root, eid, verify=verify, manifest=manifest) for eid in ids]


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
        pixels.write_png(episode_dir / row["file"], rgb)
    write_steps(episode_dir / STEPS_FILE, states)
    atomic_write_text(episode_dir / EPISODE_FILE, json.dumps(metadata, indent=1) + "\n")
    return episode_dir
