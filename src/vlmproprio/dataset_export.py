"""The episodes as a Hugging Face ``datasets`` dataset on disk: Parquet files and a dataset card.

``export_dataset(fixtures, out)`` (CLI: ``vlmproprio export-dataset OUT``) writes::

    OUT/README.md                           dataset card: YAML metadata (configs, features, splits, license)
                                            + how the episodes were recorded + the paper to cite
    OUT/frames/test-00000-of-00001.parquet   one row per sampled frame (the default config)
    OUT/episodes/test-00000-of-00001.parquet one row per episode: task, object, action, instruction, target, ...
    OUT/phases/test-00000-of-00001.parquet   one row per ground-truth phase span

so that ``datasets.load_dataset(OUT)`` gives the frames and ``load_dataset(OUT, "episodes")`` /
``load_dataset(OUT, "phases")`` the episode-level tables, each with one split, ``test`` (the suite is an
evaluation set; nothing here is meant for training).

What is exact: every image column holds the fixture's PNG file byte for byte (so decoded pixels are equal
too), and the states are float64 as recorded (``List(float64)``): a user who renders the paper's prompts
from the dataset gets the suite's numbers, not float32 roundings of them. The export reads the fixtures
through ``vlmproprio.episodes`` (manifest verified) and never re-renders. The ``datasets`` package is only
needed here (``pip install 'vlmproprio[dataset]'``).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from vlmproprio.episodes import EE_DIM, JOINT_DIM, STATE_CONVENTIONS, Episode, load_episodes
from vlmproprio.errors import VlmproprioError

SPLIT = "test"
FRAMES, EPISODES, PHASES = "frames", "episodes", "phases"
CONFIGS = (FRAMES, EPISODES, PHASES)
CARD_NAME = "README.md"
LICENSE = "mit"  # the project's licence (pyproject.toml); the fixtures are the project's own recordings

CITATION = """\
@misc{suzuki2025proprioception,
  title  = {Proprioception Enhances Vision Language Model in Generating Captions and Subtask Segmentations
            for Robot Task},
  author = {Suzuki, Kanata and Shimizu, Shota and Ogata, Tetsuya},
  year   = {2025},
  note   = {Waseda University}
}"""


class DatasetExportError(VlmproprioError):
    """An export that cannot be written; the message names the folder and what to do."""


@dataclass(frozen=True)
class ExportSummary:
    out: Path
    episodes: int
    frames: int
    phases: int
    bytes: int

    def line(self) -> str:
        return (
            f"{self.out}: {self.episodes} episodes, {self.frames} frames, {self.phases} phase spans "
            f"({self.bytes / 1e6:.1f} MB of Parquet); load with datasets.load_dataset({str(self.out)!r})"
        )


def _datasets():
    try:
        import datasets
    except ImportError as exc:
        raise DatasetExportError(
            f"exporting a dataset needs the Hugging Face datasets package (pip install 'vlmproprio[dataset]'): {exc}"
        ) from exc
    return datasets


# ---------------------------------------------------------------------------------------------- features


# Column types per config, in column order: a datasets Value dtype, IMAGE, or (dtype, length) for a list
# (length None: any length).
IMAGE = "image"
COLUMNS: dict[str, dict[str, str | tuple[str, int | None]]] = {
    FRAMES: {
        "episode_id": "string",
        "task": "string",
        "frame_index": "int32",
        "step": "int32",
        "image": IMAGE,
        "joints": ("float64", JOINT_DIM),
        "ee": ("float64", EE_DIM),
        "phase": "string",
        "direction": "string",
        "pixel_sha256": "string",
    },
    EPISODES: {
        "episode_id": "string",
        "task": "string",
        "env_name": "string",
        "target_object": "string",
        "action": "string",
        "instruction": "string",
        "target_bin_index": "int32",  # None for tasks without a target compartment
        "target_bin_row": "string",
        "target_bin_side": "string",
        "target_bin_description": "string",
        "seed": "int64",
        "steps": "int32",
        "stride": "int32",
        "n_frames": "int32",
        "camera": "string",
        "image_width": "int32",
        "image_height": "int32",
        "success": "bool",
        "phase_names": ("string", None),
        "direction_vocab": ("string", None),
        "versions": "string",  # JSON object: robosuite, mujoco, vlmproprio
        "extra": "string",  # JSON object: task-specific facts (e.g. the door hinge angle)
    },
    PHASES: {
        "episode_id": "string",
        "task": "string",
        "phase_index": "int32",
        "name": "string",
        "start_step": "int32",
        "end_step": "int32",  # inclusive
        "first_frame": "int32",  # the sampled frames inside the span (-1 when none)
        "last_frame": "int32",
    },
}


def _feature(ds, kind: str | tuple[str, int | None]):
    if kind == IMAGE:
        return ds.Image()
    if isinstance(kind, tuple):
        dtype, length = kind
        return ds.List(ds.Value(dtype)) if length is None else ds.List(ds.Value(dtype), length=length)
    return ds.Value(kind)


def features(config: str):
    """The ``datasets.Features`` of one config (images as ``Image``, state vectors as float64 lists)."""
    ds = _datasets()
    if config not in COLUMNS:
        raise ValueError(f"unknown config {config!r} (known: {', '.join(CONFIGS)})")
    return ds.Features({name: _feature(ds, kind) for name, kind in COLUMNS[config].items()})


# ---------------------------------------------------------------------------------------------- rows


def frame_columns(episodes: Sequence[Episode]) -> dict[str, list]:
    cols: dict[str, list] = {name: [] for name in features(FRAMES)}
    for ep in episodes:
        for f in ep.frames:
            cols["episode_id"].append(ep.episode_id)
            cols["task"].append(ep.task)
            cols["frame_index"].append(f.index)
            cols["step"].append(f.step)
            # the PNG file as it is: decoded pixels are then equal by construction, and so is what a model is sent
            cols["image"].append({"bytes": f.image_bytes(), "path": f"{ep.episode_id}/{f.image_path.name}"})
            cols["joints"].append(list(f.joints))
            cols["ee"].append(list(f.ee))
            cols["phase"].append(f.phase)
            cols["direction"].append(f.direction)
            cols["pixel_sha256"].append(f.image_sha256)
    return cols


def episode_columns(episodes: Sequence[Episode]) -> dict[str, list]:
    cols: dict[str, list] = {name: [] for name in features(EPISODES)}
    for ep in episodes:
        tb = ep.target_bin
        row = {
            "episode_id": ep.episode_id,
            "task": ep.task,
            "env_name": ep.env_name,
            "target_object": ep.target_object,
            "action": ep.action,
            "instruction": ep.instruction,
            "target_bin_index": None if tb is None else tb.index,
            "target_bin_row": None if tb is None else tb.row,
            "target_bin_side": None if tb is None else tb.side,
            "target_bin_description": None if tb is None else tb.description,
            "seed": ep.seed,
            "steps": ep.steps,
            "stride": ep.stride,
            "n_frames": len(ep.frames),
            "camera": ep.camera,
            "image_width": ep.image_size[0],
            "image_height": ep.image_size[1],
            "success": ep.success,
            "phase_names": list(ep.phase_names),
            "direction_vocab": list(ep.direction_vocab),
            "versions": json.dumps(ep.versions, sort_keys=True),
            "extra": json.dumps(ep.extra, sort_keys=True),
        }
        for k, v in row.items():
            cols[k].append(v)
    return cols


def phase_columns(episodes: Sequence[Episode]) -> dict[str, list]:
    cols: dict[str, list] = {name: [] for name in features(PHASES)}
    for ep in episodes:
        for i, p in enumerate(ep.phases):
            inside = [f.index for f in ep.frames if p.start_step <= f.step <= p.end_step]
            row = {
                "episode_id": ep.episode_id,
                "task": ep.task,
                "phase_index": i,
                "name": p.name,
                "start_step": p.start_step,
                "end_step": p.end_step,
                "first_frame": inside[0] if inside else -1,
                "last_frame": inside[-1] if inside else -1,
            }
            for k, v in row.items():
                cols[k].append(v)
    return cols


# ---------------------------------------------------------------------------------------------- card


def _recording_text(episodes: Sequence[Episode]) -> str:
    """How the episodes were made, from their own metadata (a fixture set may mix recorded and imported ones)."""
    versions = "; ".join(sorted({", ".join(f"{k} {v}" for k, v in sorted(e.versions.items())) for e in episodes}))
    sizes = ", ".join(sorted({f"{w}x{h}" for w, h in (e.image_size for e in episodes)}))
    strides = ", ".join(str(n) for n in sorted({e.stride for e in episodes}))
    imported = [e for e in episodes if "demo" in e.extra]  # vlmproprio.record.demos names the source demo there
    scripted = len(episodes) - len(imported)
    parts = [
        f"Simulated with robosuite and MuJoCo ({versions}): a Panda arm with robosuite's default OSC_POSE "
        f"controller at 20 Hz, rendered headless at {sizes}, one frame every {strides} sim steps from step 0 "
        "(cameras per task in the table above)."
    ]
    if scripted:
        parts.append(
            f"{scripted} episodes were driven by vlmproprio's scripted operators, which move at a human pace and "
            "know which subtask they are in at every step: their ground-truth phases come from the operator."
        )
    if imported:
        parts.append(
            f"{len(imported)} episodes are robosuite/robomimic demonstrations replayed by `vlmproprio import-demos FILE.hdf5 --out DIR` "
            "(the source file and demo are in the episodes config's `extra`); their phases come from simulator "
            "signals (gripper, lever and hinge angles, object height and position)."
        )
    parts.append(
        "Motion directions come from the grip site's displacement over one frame interval. Every file was frozen "
        "with a sha256 manifest; this export was read through vlmproprio's verified loader, never re-rendered."
    )
    return "\n".join(textwrap.wrap(" ".join(parts), width=110, break_on_hyphens=False))


def _card_body(episodes: Sequence[Episode], counts: dict[str, int]) -> str:
    by_task: dict[str, list[Episode]] = {}
    for ep in episodes:
        by_task.setdefault(ep.task, []).append(ep)
    task_lines = "\n".join(
        f"| {task} | {len(eps)} | {sum(len(e.frames) for e in eps)} | {eps[0].camera} | "
        f"{', '.join(sorted({e.env_name for e in eps}))} |"
        for task, eps in by_task.items()
    )
    conventions = "\n".join(f"- `{k}`: {v}" for k, v in STATE_CONVENTIONS.items())
    return f"""
# vlmproprio episodes

Robot episodes for the question *does giving a vision-language model the robot's proprioception (joint angles,
end-effector pose) make its captions and subtask segmentations better?*, exported by the vlmproprio
benchmark (`vlmproprio export-dataset OUT`). The method and the tasks follow Suzuki,
Shimizu & Ogata, "Proprioception Enhances Vision Language Model in Generating Captions and Subtask
Segmentations for Robot Task" (2025).

| task | episodes | frames | camera | environment |
|---|---|---|---|---|
{task_lines}

## Configs

- `frames` (default): one row per sampled frame ({counts[FRAMES]} rows): `episode_id`, `task`, `frame_index`,
  `step` (sim step), `image` (RGB PNG, the fixture file byte for byte), `joints` (8 float64),
  `ee` (6 float64), ground-truth `phase` and motion `direction`, `pixel_sha256` (sha256 of the decoded pixels
  as vlmproprio computes it).
- `episodes`: one row per episode ({counts[EPISODES]} rows): task, environment, target object, action, an
  instruction in words, the target compartment (pick-and-place), seed, steps, stride, camera, image size,
  success, phase names, direction vocabulary, software versions and task-specific facts (JSON strings).
- `phases`: one row per ground-truth phase span ({counts[PHASES]} rows), in sim steps and in sampled frames.

```python
from datasets import load_dataset
frames = load_dataset("path/to/this/folder", split="test")            # the frames config
episodes = load_dataset("path/to/this/folder", "episodes", split="test")
```

## How it was recorded

{_recording_text(episodes)}

State conventions:
{conventions}

## Intended use

Evaluation only (split `test`): captioning and subtask segmentation of robot episodes with and without
proprioception. The inspect_ai task `vlmproprio/proprio_captions` runs the paper's method on these episodes
and scores it with vlmproprio's rubric and segmentation.

## Citation

The method and tasks are those of:

```bibtex
{CITATION}
```
"""


def write_card(out: Path, episodes: Sequence[Episode], infos: dict, counts: dict[str, int]) -> Path:
    """README.md with the YAML metadata written by datasets' and huggingface_hub's own card classes."""
    from datasets.info import DatasetInfosDict
    from datasets.utils.metadata import MetadataConfigs
    from huggingface_hub import DatasetCard, DatasetCardData

    tasks = sorted({ep.task for ep in episodes})
    data = DatasetCardData(
        license=LICENSE,
        pretty_name="vlmproprio robot episodes (proprioception for VLM captioning and segmentation)",
        language=["en"],
        task_categories=["image-to-text", "robotics"],
        tags=["robotics", "proprioception", "robosuite", "captioning", "segmentation", "vlmproprio", *tasks],
        size_categories=["n<1K"] if counts[FRAMES] < 1000 else ["1K<n<10K"],
    )
    DatasetInfosDict(infos).to_dataset_card_data(data)
    configs = {
        name: {"data_files": [{"split": SPLIT, "path": f"{name}/{SPLIT}-*"}], **({"default": True} if i == 0 else {})}
        for i, name in enumerate(CONFIGS)
    }
    MetadataConfigs(configs).to_dataset_card_data(data)
    card = DatasetCard(f"---\n{data.to_yaml()}\n---\n{_card_body(episodes, counts)}")
    path = out / CARD_NAME
    path.write_text(str(card), encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------- export


def _check_out(fixtures: Path, out: Path, overwrite: bool) -> None:
    fx, o = fixtures.resolve(), out.resolve()
    if o == fx or fx in o.parents:
        raise DatasetExportError(f"{out}: inside the fixture folder {fixtures}; export somewhere else")
    if out.exists() and not out.is_dir():
        raise DatasetExportError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        ours = (out / CARD_NAME).is_file() and all(
            p.name in (CARD_NAME, *CONFIGS) or p.name.startswith(".") for p in out.iterdir()
        )
        if not overwrite:
            raise DatasetExportError(f"{out}: not empty; pass --overwrite to replace an earlier export there")
        if not ours:
            raise DatasetExportError(f"{out}: holds files that are not an export of ours; choose an empty folder")


def export_dataset(
    fixtures: str | Path,
    out: str | Path,
    episode_ids: Sequence[str] | None = None,
    *,
    overwrite: bool = False,
) -> ExportSummary:
    """Write the fixtures' episodes (all, or ``episode_ids``) as a Parquet dataset with a card into ``out``.

    The export is built in a temporary folder next to ``out`` and moved into place at the end, so an
    interrupted export leaves no half dataset behind."""
    ds = _datasets()
    fixtures, out = Path(fixtures), Path(out)
    _check_out(fixtures, out, overwrite)
    episodes = load_episodes(fixtures, episode_ids)
    columns = {FRAMES: frame_columns(episodes), EPISODES: episode_columns(episodes), PHASES: phase_columns(episodes)}
    out.parent.mkdir(parents=True, exist_ok=True)
    from datasets.utils import are_progress_bars_disabled, disable_progress_bars, enable_progress_bars

    bars = not are_progress_bars_disabled()
    disable_progress_bars()  # one bar per tiny table is noise; the summary line says what was written
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".partial"))
    try:
        tmp.chmod(0o755)  # mkdtemp makes an owner-only folder; a dataset is meant to be shared
        infos, counts, size = {}, {}, 0
        for name in CONFIGS:
            table = ds.Dataset.from_dict(columns[name], features=features(name), split=SPLIT)
            path = tmp / name / f"{SPLIT}-00000-of-00001.parquet"
            path.parent.mkdir(parents=True)
            table.to_parquet(str(path))
            n_bytes = path.stat().st_size
            splits = ds.SplitDict()
            splits.add(ds.SplitInfo(name=SPLIT, num_bytes=n_bytes, num_examples=len(table)))
            info = ds.DatasetInfo(
                features=table.features, splits=splits, download_size=n_bytes, dataset_size=n_bytes, config_name=name
            )
            infos[name] = info
            counts[name] = len(table)
            size += n_bytes
        write_card(tmp, episodes, infos, counts)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if bars:
            enable_progress_bars()
    return ExportSummary(out, counts[EPISODES], counts[FRAMES], counts[PHASES], size)
