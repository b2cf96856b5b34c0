"""A per-task summary of a fixture set, after verifying every file against the manifest, every steps.npz against
its episode.json and every frame's pixels against its pixel_sha256."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vlmproprio.episodes import check_steps, frame_images, load_episodes, read_manifest, verify_files


@dataclass(frozen=True)
class TaskSummary:
    task: str
    episodes: int
    frames: int
    mean_steps: float
    min_steps: int
    max_steps: int
    mean_frames: float
    mb: float


@dataclass(frozen=True)
class FixtureSummary:
    root: Path
    files_verified: int
    tasks: list[TaskSummary]
    episodes_mb: float
    frames_verified: int = 0


def fixture_summary(root: Path) -> FixtureSummary:
    root = Path(root)
    manifest = read_manifest(root)
    checked = verify_files(root, "", manifest)
    episodes = load_episodes(root, verify=False)  # every file was just verified
    # what a regenerated manifest would bless: a steps.npz or a frame swapped in from elsewhere, a flipped pixel
    for e in episodes:
        check_steps(e)
        frame_images(e.frames)
    tasks = []
    for task in sorted({e.task for e in episodes}):
        eps = [e for e in episodes if e.task == task]
        size = sum(p.stat().st_size for e in eps for p in e.root.rglob("*") if p.is_file())
        steps = [e.steps for e in eps]
        frames = [len(e.frames) for e in eps]
        tasks.append(
            TaskSummary(
                task=task,
                episodes=len(eps),
                frames=sum(frames),
                mean_steps=sum(steps) / len(steps),
                min_steps=min(steps),
                max_steps=max(steps),
                mean_frames=sum(frames) / len(frames),
                mb=size / 1e6,
            )
        )
    n_frames = sum(len(e.frames) for e in episodes)
    return FixtureSummary(root, checked, tasks, sum(t.mb for t in tasks), n_frames)


def format_summary(s: FixtureSummary) -> str:
    lines = [
        f"{s.root}: {s.files_verified} files match {s.root / 'manifest.json'}; steps.npz and the pixels of "
        f"{s.frames_verified} frames match their episode.json"
    ]
    lines.append(f"{'task':<12}{'episodes':>9}{'frames':>8}{'frames/ep':>10}{'mean steps':>11}{'min-max':>10}{'MB':>7}")
    for t in s.tasks:
        lines.append(
            f"{t.task:<12}{t.episodes:>9}{t.frames:>8}{t.mean_frames:>10.1f}{t.mean_steps:>11.1f}"
            f"{f'{t.min_steps}-{t.max_steps}':>10}{t.mb:>7.1f}"
        )
    lines.append(f"episodes total: {s.episodes_mb:.1f} MB")
    return "\n".join(lines)
