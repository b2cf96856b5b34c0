"""What a correct caption of one episode says, derived from the episode's ground truth and its lexicon.

Expected directions come from the hand's net displacement in the phase a motion names (read from
``steps.npz``, or from the sampled frames' direction labels when an episode has no full-rate states), and
the camera's pose decides the words that depend on it (image left/right, top/bottom).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np

from vlmproprio.episodes import Episode
from vlmproprio.errors import VlmproprioError
from vlmproprio.scoring.lexicon import (
    AXES,
    CAMERAS_FILE,
    LEXICON_PACKAGE,
    Lexicon,
    ScoringError,
    _read_lexicon_file,
    load_lexicon,
)

# Directions whose meaning never depends on the camera: the robot's frame (forward = +x, left = +y, up = +z).
ROBOT_VECTORS: dict[str, tuple[float, float, float]] = {
    "forward": (1.0, 0.0, 0.0),
    "backward": (-1.0, 0.0, 0.0),
    "robot_left": (0.0, 1.0, 0.0),
    "robot_right": (0.0, -1.0, 0.0),
    "up": (0.0, 0.0, 1.0),
    "down": (0.0, 0.0, -1.0),
}
# A hand displacement shorter than this (m) names no direction (as vlmproprio.primitives.MIN_MOVE_M).
MIN_MOVE_M = 0.01
# A camera axis counts as one of the robot's when their cosine is at least this.
AXIS_COS = 0.5


@dataclass(frozen=True)
class CameraAxes:
    """Image right, image up and viewing direction of an episode's camera, unit vectors in the robot's frame."""

    right: tuple[float, float, float]
    up: tuple[float, float, float]
    view: tuple[float, float, float]
    source: str


@lru_cache(maxsize=1)
def _camera_table() -> dict:
    data, _ = _read_lexicon_file(CAMERAS_FILE)
    if not isinstance(data.get("envs"), dict):
        raise ScoringError(f"lexicon {LEXICON_PACKAGE}/{CAMERAS_FILE}: missing 'envs'")
    return data["envs"]


def _axes(d: dict, where: str) -> CameraAxes:
    try:
        vecs = [np.asarray(d[k], dtype=float) for k in ("right", "up", "view")]
    except (KeyError, TypeError, ValueError) as exc:
        raise ScoringError(f"{where}: camera axes need right, up and view as 3-vectors ({exc})") from exc
    if any(v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) < 1e-6 for v in vecs):
        raise ScoringError(f"{where}: camera axes need right, up and view as non-zero 3-vectors")
    r, u, v = (tuple(float(x) for x in vec / np.linalg.norm(vec)) for vec in vecs)
    return CameraAxes(r, u, v, where)


def camera_axes(episode: Episode) -> CameraAxes | None:
    """The pose of the episode's camera: its own (episode.json extra.camera_axes, written by the demo importer),
    else the shipped table (lexicons/cameras.json by env and camera name), else None (unknown camera)."""
    own = episode.extra.get("camera_axes") if isinstance(episode.extra, dict) else None
    if own is not None:
        return _axes(own, f"episode {episode.episode_id}: episode.json extra.camera_axes")
    for env_prefix, cams in _camera_table().items():
        if episode.env_name.startswith(env_prefix) and episode.camera in cams:
            return _axes(cams[episode.camera], f"{CAMERAS_FILE}: {env_prefix}/{episode.camera}")
    return None


def direction_vectors(camera: CameraAxes | None) -> dict[str, np.ndarray]:
    """Unit vector of every direction value in the robot's frame; plain left/right are the image's when the
    camera is known, else the robot's (the shipped bin camera's convention: image left = robot left)."""
    out = {k: np.asarray(v) for k, v in ROBOT_VECTORS.items()}
    if camera is None:
        out["left"], out["right"] = out["robot_left"], out["robot_right"]
    else:
        out["right"] = np.asarray(camera.right)
        out["left"] = -np.asarray(camera.right)
    return out


@dataclass(frozen=True)
class MotionExpectation:
    name: str
    groups: tuple[str, ...]
    expected: tuple[str, ...]
    source: str  # where ``expected`` comes from, for the audit
    opposite: tuple[str, ...] = ()
    returns: tuple[str, ...] = ()  # directions of the motion's return phase (the lever springing back up)
    return_cues: tuple[str, ...] = ()


@dataclass(frozen=True)
class Expectation:
    """What a correct caption of one episode says: from the episode's ground truth and the lexicon."""

    task: str
    target_object: str
    target_row: str | None
    target_side: str | None  # the robot's side of the target compartment (left | right)
    motions: tuple[MotionExpectation, ...]
    image_side: str | None = None  # the side word in the camera's image; None when the camera does not tell
    image_rows: tuple[tuple[str, str], ...] = ()  # (image word top|bottom, row near|far) for this camera
    target_column: str | None = None  # next_to_source | away_from_source
    camera: str = ""  # where the camera pose came from

    def to_dict(self) -> dict:
        return asdict(self)


def _consistent_steps(episode: Episode):
    """The full-rate states when they belong to this episode (one row per sim step), else None."""
    path = episode.root / "steps.npz"
    if not path.is_file():
        return None
    try:
        st = episode.step_states
    except VlmproprioError:
        return None
    if len(st.step) != episode.steps + 1 or (len(st.phase) and int(st.phase.max()) >= len(episode.phase_names)):
        return None
    return st


def phase_displacement(episode: Episode, phase_pattern: str) -> tuple[np.ndarray | None, str]:
    """The hand's net displacement (m, robot frame) over the steps of the phases matching the pattern.

    From ``steps.npz`` when the episode has one; else (an episode without full-rate states) a pseudo
    displacement from the sampled frames' direction labels, one unit vector per moving frame."""
    pat = re.compile(phase_pattern, re.IGNORECASE)
    st = _consistent_steps(episode)
    if st is not None:
        names = [i for i, n in enumerate(episode.phase_names) if pat.search(n)]
        idx = np.flatnonzero(np.isin(st.phase, names))
        if not len(idx):
            return None, f"steps.npz: no step in a phase matching {phase_pattern!r}"
        first, last = int(idx[0]), int(idx[-1])
        delta = st.ee[last, :3] - st.ee[first, :3]
        where = ", ".join(repr(episode.phase_names[i]) for i in names)
        d = "(" + ", ".join(f"{x:+.3f}" for x in delta) + ")"
        return (
            delta,
            f"steps.npz: hand displacement {d} m over steps {int(st.step[first])}..{int(st.step[last])} ({where})",
        )
    moving = [f for f in episode.frames if pat.search(f.phase) and f.direction not in ("still", "")]
    if not moving:
        return None, f"ground truth: no moving frame in a phase matching {phase_pattern!r}"
    total = np.zeros(3)
    for f in moving:
        v = sum(
            (np.asarray(ROBOT_VECTORS["robot_" + w if w in ("left", "right") else w]) for w in f.direction.split("+")),
            np.zeros(3),
        )
        total += v / np.linalg.norm(v)
    idx = [f.index for f in moving]
    return (
        total,
        f"ground truth: direction labels of {len(moving)} moving frames {idx[0]}..{idx[-1]} in phase {moving[0].phase!r}",
    )


def directions_of(delta: np.ndarray | None, axes: Sequence[str], min_share: float, vectors: dict[str, np.ndarray]):
    """(expected, opposite) direction values for a displacement restricted to ``axes``: a value is expected
    when its unit vector carries at least ``min_share`` of the displacement, opposite when it carries that
    much against it."""
    if delta is None:
        return (), ()
    d = np.array([delta[i] if a in axes else 0.0 for i, a in enumerate(AXES)])
    norm = float(np.linalg.norm(d))
    if norm < MIN_MOVE_M:
        return (), ()
    share = {k: float(d @ v) / norm for k, v in vectors.items()}
    return tuple(sorted(k for k, c in share.items() if c >= min_share)), tuple(
        sorted(k for k, c in share.items() if c <= -min_share)
    )


def _image_words(cam: CameraAxes | None) -> tuple[str | None, tuple[tuple[str, str], ...]]:
    """(the image side of the robot's left, image row words -> near/far) for a camera; None/() where it does not tell."""
    if cam is None:  # the shipped convention: image left = robot left, top of the image = far from the robot
        return "left", (("top", "far"), ("bottom", "near"))
    left_in_image = -float(np.asarray(ROBOT_VECTORS["robot_left"]) @ np.asarray(cam.right))
    side = "left" if left_in_image >= AXIS_COS else "right" if left_in_image <= -AXIS_COS else None
    far_up = float(np.asarray(ROBOT_VECTORS["forward"]) @ np.asarray(cam.up))
    rows: tuple[tuple[str, str], ...] = ()
    if far_up >= AXIS_COS:
        rows = (("top", "far"), ("bottom", "near"))
    elif far_up <= -AXIS_COS:
        rows = (("top", "near"), ("bottom", "far"))
    return side, rows


def expectation_for(episode: Episode, lexicon: Lexicon | None = None) -> Expectation:
    """What a correct caption of ``episode`` says, in the words of ``lexicon`` (default: its task's)."""
    lex = lexicon or load_lexicon(episode.task)
    cam = camera_axes(episode)
    vectors = direction_vectors(cam)
    motions = []
    for m in lex.motions:
        opposite: tuple[str, ...] = ()
        returns: tuple[str, ...] = ()
        if m.from_phase:
            delta, source = phase_displacement(episode, m.from_phase)
            expected, opposite = directions_of(delta, m.axes, m.min_share, vectors)
            if m.return_phase:
                back, back_source = phase_displacement(episode, m.return_phase)
                returns, _ = directions_of(back, m.axes, m.min_share, vectors)
                source += f"; returns {'/'.join(returns) or 'nowhere'} from {back_source}"
        else:
            expected, source = m.expected, f"lexicon {lex.task}.json"
            opposite = tuple(sorted({lex.opposite[d] for d in expected if d in lex.opposite}))
        unknown = [d for d in expected if d not in lex.opposite]
        if unknown:
            raise ScoringError(f"episode {episode.episode_id}: unknown direction words {unknown} for motion {m.name!r}")
        returns = tuple(d for d in returns if d not in expected)
        motions.append(MotionExpectation(m.name, m.groups, expected, source, opposite, returns, tuple(m.return_cues)))
    row = side = column = image_side = None
    image_rows: tuple[tuple[str, str], ...] = ()
    if lex.compartment is not None:
        if episode.target_bin is None:
            raise ScoringError(f"episode {episode.episode_id}: task {episode.task} needs a target_bin in episode.json")
        row, side = episode.target_bin.row, episode.target_bin.side
        if row not in ("near", "far") or side not in ("left", "right"):
            raise ScoringError(
                f"episode {episode.episode_id}: target_bin row/side {row!r}/{side!r} not near|far, left|right"
            )
        # robosuite's PickPlace.not_in_bin index: bit 1 set = the column away from the source bin
        column = "away_from_source" if episode.target_bin.index & 2 else "next_to_source"
        left_word, image_rows = _image_words(cam)
        if left_word is not None:
            image_side = side if left_word == "left" else lex.opposite[side]
    return Expectation(
        task=episode.task,
        target_object=lex.object_key(episode.target_object),
        target_row=row,
        target_side=side,
        motions=tuple(motions),
        image_side=image_side,
        image_rows=image_rows,
        target_column=column,
        camera=cam.source if cam else "unknown camera: image words read in the robot's frame",
    )
