"""Hand-made episodes, transcripts and whole synthetic runs for the scoring / segmentation / stats tests.

Nothing here comes from a model: captions are written from templates so that tests
know what the right scores are.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vlmproprio.conditions import CONTROLS, PAPER_CONDITIONS
from vlmproprio.episodes import (
    Episode,
    Frame,
    PhaseSpan,
    StepStates,
    TargetBin,
    episode_metadata,
    pixel_sha256,
    write_episode,
    write_manifest,
)
from vlmproprio.transcripts import FrameCaption, SceneCaption, Transcript, write_transcript

DOOR_PHASES = ("approach", "grasp handle", "turn handle down", "pull door open", "release/retreat")
BIN_ROWS_SIDES = {0: ("near", "right"), 1: ("far", "right"), 2: ("near", "left"), 3: ("far", "left")}
# every condition but both_permuted (added after these helpers; the tests' expected numbers are for this set)
CONDITIONS = tuple(c for c in (*PAPER_CONDITIONS, *CONTROLS) if c != "both_permuted")


def bin_phases(k: int) -> tuple[str, ...]:
    return ("approach", "descend", "grasp", "lift", f"transport to bin {k}", "lower", "release", "retreat")


def make_episode(
    task: str,
    phases: Sequence[str],
    directions: Sequence[str] | None = None,
    *,
    episode_id: str = "ep_00",
    target_bin: TargetBin | None = None,
    target_object: str | None = None,
) -> Episode:
    """An in-memory Episode with one frame per phase label (no files behind it)."""
    directions = list(directions) if directions is not None else ["still"] * len(phases)
    frames = tuple(
        Frame(i, i * 20, Path(f"frames/{i:03d}.png"), "", (0.0,) * 8, (0.0,) * 6, p, d)
        for i, (p, d) in enumerate(zip(phases, directions, strict=True))
    )
    return Episode(
        episode_id=episode_id,
        root=Path("."),
        task=task,
        env_name="Door" if task == "door" else "PickPlaceCereal",
        target_object=target_object or ("door" if task == "door" else "cereal"),
        action="open" if task == "door" else "pick_place",
        instruction="open the door" if task == "door" else "put the cereal box into the target bin",
        target_bin=target_bin,
        seed=0,
        steps=len(frames) * 20,
        stride=20,
        camera="sideview",
        image_size=(8, 8),
        versions={},
        success=True,
        phase_names=tuple(dict.fromkeys(phases)),
        direction_vocab=("still",),
        phases=(),
        frames=frames,
    )


def door_episode(episode_id: str = "door_00") -> Episode:
    phases = ["approach"] * 2 + ["grasp handle", "turn handle down", "turn handle down"]
    phases += ["pull door open"] * 3 + ["release/retreat"]
    dirs = [
        "forward",
        "forward+down",
        "still",
        "down",
        "down",
        "backward+left",
        "backward+left",
        "backward",
        "backward",
    ]
    return make_episode("door", phases, dirs, episode_id=episode_id)


def bin_episode(k: int = 3, episode_id: str = "bin3_00") -> Episode:
    row, side = BIN_ROWS_SIDES[k]
    phases = ["approach", "descend", "grasp", "lift"] + [f"transport to bin {k}"] * 3 + ["lower", "release", "retreat"]
    fwd = "forward" if row == "far" else "backward"
    dirs = ["forward", "down", "still", "up", f"{fwd}+left", "left", f"{fwd}+left", "down", "still", "up"]
    tb = TargetBin(k, row, side, f"the {row} {side} compartment")
    return make_episode("pick_place", phases, dirs, episode_id=episode_id, target_bin=tb)


# ---------------------------------------------------------------------------------------------- on disk


def _phase_plan(task: str, k: int, n_frames: int) -> list[tuple[str, str]]:
    """(phase, direction) per frame: phases spread over the episode in fixed proportions."""
    if task == "door":
        parts = [
            ("approach", "forward", 0.25),
            ("grasp handle", "still", 0.1),
            ("turn handle down", "down", 0.2),
            ("pull door open", "backward+left", 0.3),
            ("release/retreat", "backward", 0.15),
        ]
    else:
        row, _ = BIN_ROWS_SIDES[k]
        fwd = "forward" if row == "far" else "backward"
        parts = [
            ("approach", "forward", 0.15),
            ("descend", "down", 0.1),
            ("grasp", "still", 0.08),
            ("lift", "up", 0.1),
            (f"transport to bin {k}", f"{fwd}+left", 0.27),
            ("lower", "down", 0.1),
            ("release", "still", 0.08),
            ("retreat", "up", 0.12),
        ]
    out = []
    for phase, d, share in parts:
        out += [(phase, d)] * max(1, round(share * n_frames))
    return (out + [out[-1]] * n_frames)[:n_frames]


def write_fixture_episode(root: Path, episode_id: str, task: str, n_frames: int, k: int = 0) -> None:
    plan = _phase_plan(task, k, n_frames)
    rng = np.random.default_rng(zlib.crc32(episode_id.encode()))
    ee = np.cumsum(rng.normal(0, 0.02, size=(n_frames, 6)), axis=0) + np.array([0.5, 0.0, 1.0, 3.1, 0.0, 0.0])
    joints = np.cumsum(rng.normal(0, 0.05, size=(n_frames, 8)), axis=0)
    img = np.zeros((8, 8, 3), dtype=np.uint8)
    rows = []
    for i, (phase, d) in enumerate(plan):
        rows.append(
            {
                "index": i,
                "step": i * 20,
                "file": f"frames/{i:03d}.png",
                "pixel_sha256": pixel_sha256(img),
                "joints": [float(x) for x in joints[i]],
                "ee": [float(x) for x in ee[i]],
                "phase": phase,
                "direction": d,
            }
        )
    names = list(dict.fromkeys(p for p, _ in plan))
    spans = []
    for name in names:
        idx = [i for i, (p, _) in enumerate(plan) if p == name]
        spans.append(PhaseSpan(name, idx[0] * 20, idx[-1] * 20 + 19))
    row, side = BIN_ROWS_SIDES.get(k, ("near", "right"))
    meta = episode_metadata(
        episode_id=episode_id,
        task=task,
        env_name="Door" if task == "door" else "PickPlaceCereal",
        target_object="door" if task == "door" else "cereal",
        action="open" if task == "door" else "pick_place",
        instruction="open the door" if task == "door" else f"put the cereal into the {row} {side} compartment",
        target_bin=None if task == "door" else TargetBin(k, row, side, f"{row} {side}"),
        seed=0,
        steps=n_frames * 20,
        stride=20,
        camera="sideview",
        image_size=(8, 8),
        versions={},
        success=True,
        phase_names=names,
        direction_vocab=["still", "forward", "backward", "up", "down", "left", "right"],
        phases=spans,
        frame_rows=rows,
    )
    n = n_frames
    states = StepStates(
        step=np.arange(n, dtype=np.int64),
        joints=joints,
        ee=ee,
        phase=np.zeros(n, dtype=np.int64),
        direction=np.zeros(n, dtype=np.int64),
    )
    episode_dir = write_episode(root, meta, [img] * n_frames, states)
    # no full-rate states: these synthetic episodes have none that agree with their frames (loading checks
    # that a steps.npz does), and scoring then reads the frames' direction labels, as these tests intend
    (episode_dir / "steps.npz").unlink()


def _frame_caption(task: str, phase: str, direction: str, cond: str, ee: Sequence[float], i: int, eid: str = "") -> str:
    words = direction.replace("+", " and ")
    if task == "door":
        base = {
            "approach": f"The robot arm moves {words} toward the door handle with its gripper open",
            "grasp handle": "The gripper closes around the door handle and holds it firmly",
            "turn handle down": "The robot turns the door handle downward to release the latch",
            "pull door open": "The robot pulls the door open toward itself while holding the handle",
            "release/retreat": "The gripper opens and the arm moves back away from the open door",
        }[phase]
    else:
        key = phase.split(" ")[0]
        base = {
            "approach": f"The robot arm moves {words} above the cereal box in the source bin",
            "descend": "The arm descends down toward the cereal box with the gripper open",
            "grasp": "The gripper closes on the cereal box and grasps it",
            "lift": "The robot lifts the cereal box up out of the source bin",
            "transport": f"The robot carries the cereal box {words} toward the target bin",
            "lower": "The robot lowers the cereal box down into the compartment",
            "release": "The gripper opens and releases the cereal box in the bin",
            "retreat": "The arm moves up and away from the bin after placing the box",
        }[key]
    if cond == "none":
        clip = f" of clip {zlib.crc32(eid.encode())}" if eid else ""  # unique per episode, no lexicon words
        return f"{base} in frame {i}{clip}."
    x, y, z = ee[:3]
    return f"{base}; the hand is at x {x:.3f}, y {y:.3f}, z {z:.3f} ({cond}, frame {i})."


def _final_caption(task: str, cond: str, k: int) -> str:
    row, side = BIN_ROWS_SIDES.get(k, ("near", "right"))
    if task == "door":
        if cond == "none":
            return "The robot opens the door."
        return "Grasp the door handle, turn it downward and then pull the door open toward the robot."
    if cond == "none":
        return "The robot picks up the cereal box and places it in the bin."
    return f"Pick up the cereal box, lift it up and place it in the {row} {side} compartment of the target bin."


def write_synthetic_run(
    run_dir: Path,
    fixtures: Path,
    *,
    model: str = "synthetic",
    n_door: int = 10,
    n_per_bin: int = 3,
    n_frames: int = 30,
    conditions: Sequence[str] = CONDITIONS,
    missing: dict[tuple[str, str], list[int]] | None = None,
) -> list[str]:
    """Fixtures + a run directory with one template transcript per (episode, condition); returns episode ids."""
    ids = []
    for s in range(n_door):
        eid = f"door_{s:02d}"
        write_fixture_episode(fixtures, eid, "door", n_frames)
        ids.append(eid)
    for k in range(4):
        for s in range(n_per_bin):
            eid = f"bin{k}_{s:02d}"
            write_fixture_episode(fixtures, eid, "pick_place", n_frames - 3, k)
            ids.append(eid)
    write_manifest(fixtures)
    from vlmproprio.episodes import load_episodes

    eps = {e.episode_id: e for e in load_episodes(fixtures, ids)}
    missing = missing or {}
    for eid in ids:
        ep = eps[eid]
        k = ep.target_bin.index if ep.target_bin else 0
        for cond in conditions:
            gone = set(missing.get((eid, cond), []))
            frames = [
                FrameCaption(
                    f.index,
                    f.step,
                    "" if f.index in gone else _frame_caption(ep.task, f.phase, f.direction, cond, f.ee, f.index, eid),
                    "missing" if f.index in gone else "ok",
                )
                for f in ep.frames
            ]
            groups = [list(range(s, min(s + 5, len(frames)))) for s in range(0, len(frames), 5)]
            scenes = [
                SceneCaption(g, tuple(idx), frames[idx[0]].text or frames[idx[-1]].text, "ok")
                for g, idx in enumerate(groups)
            ]
            t = Transcript(
                model=model,
                episode_id=eid,
                task=ep.task,
                condition=cond,
                prompt_version="test",
                frames=frames,
                scenes=scenes,
                final=_final_caption(ep.task, cond, k),
                final_status="ok",
            )
            write_transcript(run_dir, t)
    entry = {"name": model, "slug": model, "pipeline": {"prompt_version": "test"}}  # as the runner writes it
    manifest = {"fixtures": str(fixtures), "models": [entry], "conditions": list(conditions), "episodes": ids}
    (run_dir / "run.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return ids


# ---------------------------------------------------------------------------------------------- fake embeddings


def fake_vector(text: str, dim: int = 16) -> np.ndarray:
    """A deterministic stand-in embedding: captions that start alike point alike (phase templates)."""
    import hashlib

    head = " ".join(text.split()[:6])
    bucket = int(hashlib.sha256(head.encode()).hexdigest(), 16) % dim
    noise = np.frombuffer(hashlib.sha256(text.encode()).digest()[:dim], dtype=np.uint8).astype(np.float32) / 255.0
    v = 0.25 * noise
    v[bucket] += 1.0
    return v.astype(np.float32)


def prefill_embeddings(run_dir: Path, encoder_key: str, cache_dir: Path | None = None, dim: int = 16) -> int:
    """Put a fake vector for every frame caption of the run into the embedding cache; returns how many.

    Fake vectors under a real encoder's key would poison the session's shared cache for every later test that
    embeds with that encoder (the benchmark gates did, in CI), so a real key needs an explicit, private cache_dir.
    """
    from vlmproprio.embeddings import EmbeddingStore, default_embedding_dir

    if cache_dir is None and encoder_key != fake_spec().key:
        raise AssertionError(
            f"prefill_embeddings: fake vectors for the real encoder {encoder_key!r} need a private cache_dir"
        )
    from vlmproprio.transcripts import read_transcripts

    texts = {f.text for t in read_transcripts(run_dir) for f in t.frames if f.text.strip() and f.status != "missing"}
    with EmbeddingStore(cache_dir or default_embedding_dir()) as store:
        store.put_many(encoder_key, {t: fake_vector(t, dim) for t in sorted(texts)})
    return len(texts)


def fake_spec():
    """An encoder that cannot be loaded: any attempt to compute an embedding fails loudly."""
    from vlmproprio.embeddings import EncoderSpec

    return EncoderSpec(name="fake-encoder", path="/nonexistent/fake-encoder", revision="test-1")


def score_scripted_run(run: Path, fixtures: Path, episodes: Sequence[str], conditions: Sequence[str], answers) -> None:
    """Caption the real ``episodes`` under ``conditions`` with the answer function ``answers`` (model "scripted"),
    write the run's transcripts and run.json, and score it with fake embeddings (no encoder)."""
    from vlmproprio.conditions import get_condition
    from vlmproprio.episodes import load_episodes
    from vlmproprio.evaluation import score_run
    from vlmproprio.pipeline import caption_episodes
    from vlmproprio.transcripts import write_transcripts

    eps = load_episodes(fixtures, list(episodes))
    conds = [get_condition(c) for c in conditions]
    write_transcripts(run, caption_episodes(eps, conds, answers, "scripted", progress=False))
    entry = {"name": "scripted", "slug": "scripted", "pipeline": {"prompt_version": "test"}}
    manifest = {"fixtures": str(fixtures), "models": [entry], "conditions": list(conditions), "episodes": episodes}
    (run / "run.json").write_text(json.dumps(manifest, indent=1) + "\n")
    prefill_embeddings(run, fake_spec().key)
    score_run(run, encoder=fake_spec(), progress=False)
