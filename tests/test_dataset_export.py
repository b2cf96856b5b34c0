"""The Hugging Face dataset export: every frame's pixels and states round-trip bit for bit through
``datasets.load_dataset``, the episode-level configs match the episodes, the card carries its metadata."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

# checked, not imported: collecting this module on every xdist worker must not cost datasets' and pyarrow's
# ~1 CPU s; the tests that read the export back import it (the ``datasets`` fixture)
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("datasets") is None, reason="the export needs the [dataset] extra"
)

from vlmproprio.cli import main as cli_main  # noqa: E402
from vlmproprio.dataset_export import CITATION, CONFIGS, DatasetExportError, export_dataset  # noqa: E402
from vlmproprio.episodes import EpisodeError, load_episodes, pixel_sha256  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture(scope="module")
def datasets():
    import datasets

    return datasets


@pytest.fixture(scope="module")
def episodes():
    return {ep.episode_id: ep for ep in load_episodes(FIXTURES)}


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    """The whole fixture set, exported once (~4 s)."""
    out = tmp_path_factory.mktemp("export") / "vlmproprio-episodes"
    summary = export_dataset(FIXTURES, out)
    assert (summary.episodes, summary.frames) == (22, sum(1 for _ in (FIXTURES / "episodes").glob("*/frames/*.png")))
    return out


@pytest.fixture(scope="module")
def hf_cache(tmp_path_factory) -> str:
    return str(tmp_path_factory.mktemp("hf-datasets-cache"))


def _bits(values) -> bytes:
    return np.asarray(values, dtype=np.float64).tobytes()


def test_every_frame_round_trips_bit_identically(datasets, exported, episodes, hf_cache):
    ds = datasets.load_dataset(str(exported), split="test", cache_dir=hf_cache)  # the default config: frames
    f = ds.features
    assert isinstance(f["image"], datasets.Image)
    for name, dim in (("joints", 8), ("ee", 6)):
        assert isinstance(f[name], datasets.List) and f[name].length == dim
        assert f[name].feature == datasets.Value("float64")
    assert len(ds) == sum(len(ep.frames) for ep in episodes.values())
    raw = ds.cast_column("image", datasets.Image(decode=False))
    seen = set()
    for row, raw_row in zip(ds, raw, strict=True):
        ep = episodes[row["episode_id"]]
        frame = ep.frames[row["frame_index"]]
        seen.add((ep.episode_id, frame.index))
        assert (row["task"], row["step"], row["phase"], row["direction"]) == (
            ep.task,
            frame.step,
            frame.phase,
            frame.direction,
        )
        assert raw_row["image"]["bytes"] == frame.image_bytes()  # the PNG file itself
        pixels = np.asarray(row["image"].convert("RGB"))
        # image_bytes() above checked that the file decodes to pixels hashing to image_sha256: equal hashes are
        # equal pixels, without decoding each frame a second time
        assert pixels.dtype == np.uint8 and pixel_sha256(pixels) == frame.image_sha256
        assert row["pixel_sha256"] == frame.image_sha256
        assert _bits(row["joints"]) == _bits(frame.joints)
        assert _bits(row["ee"]) == _bits(frame.ee)
    assert seen == {(e.episode_id, fr.index) for e in episodes.values() for fr in e.frames}


def test_episode_and_phase_configs_match_the_episodes(datasets, exported, episodes, hf_cache):
    meta = datasets.load_dataset(str(exported), "episodes", split="test", cache_dir=hf_cache)
    assert sorted(meta["episode_id"]) == sorted(episodes)
    for row in meta:
        ep = episodes[row["episode_id"]]
        assert row["instruction"] == ep.instruction
        assert (row["task"], row["env_name"], row["seed"], row["steps"], row["n_frames"]) == (
            ep.task,
            ep.env_name,
            ep.seed,
            ep.steps,
            len(ep.frames),
        )
        assert row["phase_names"] == list(ep.phase_names)
        assert row["target_bin_index"] == (None if ep.target_bin is None else ep.target_bin.index)
    phases = datasets.load_dataset(str(exported), "phases", split="test", cache_dir=hf_cache)
    assert len(phases) == sum(len(ep.phases) for ep in episodes.values())
    for row in phases:
        ep = episodes[row["episode_id"]]
        span = ep.phases[row["phase_index"]]
        assert (row["name"], row["start_step"], row["end_step"]) == (span.name, span.start_step, span.end_step)
        frames = [f.index for f in ep.frames if f.phase == span.name and span.start_step <= f.step <= span.end_step]
        assert (row["first_frame"], row["last_frame"]) == ((frames[0], frames[-1]) if frames else (-1, -1))


def test_card_declares_configs_features_license_and_citation(exported):
    from huggingface_hub import DatasetCard

    card = DatasetCard.load(exported / "README.md")
    data = card.data.to_dict()
    assert data["license"] == "mit"
    configs = {c["config_name"]: c for c in data["configs"]}
    assert set(configs) == set(CONFIGS)
    assert configs["frames"].get("default") is True
    infos = {c["config_name"]: c for c in data["dataset_info"]}
    assert {f["name"]: f.get("dtype", f.get("list")) for f in infos["frames"]["features"]}["image"] == "image"
    assert infos["frames"]["splits"][0]["num_examples"] == 629
    assert "Suzuki" in CITATION and CITATION in card.text
    assert "How it was recorded" in card.text and "robosuite" in card.text


def test_card_says_how_imported_episodes_were_made(episodes):
    from dataclasses import replace

    from vlmproprio.dataset_export import _recording_text

    door = episodes["door_00"]
    text = _recording_text([door, replace(door, episode_id="imp_door_01", extra={"demo": "demo_1"})])
    assert "1 episodes were driven by vlmproprio's scripted operators" in text.replace("\n", " ")
    assert "1 episodes are robosuite/robomimic demonstrations" in text.replace("\n", " ")
    assert "scripted" not in _recording_text([replace(door, extra={"demo": "demo_1"})])


def test_export_is_deterministic_and_refuses_to_clobber(datasets, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    export_dataset(FIXTURES, a, ["door_00", "bin2_01"])
    export_dataset(FIXTURES, b, ["door_00", "bin2_01"])
    files = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    with pytest.raises(DatasetExportError, match="not empty"):
        export_dataset(FIXTURES, a, ["door_00"])
    export_dataset(FIXTURES, a, ["door_00"], overwrite=True)
    assert datasets.load_dataset(str(a), split="test", cache_dir=str(tmp_path / "c")).unique("episode_id") == [
        "door_00"
    ]
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(DatasetExportError, match="not an export of ours"):
        export_dataset(FIXTURES, foreign, ["door_00"], overwrite=True)
    assert (foreign / "notes.txt").read_text() == "mine"
    with pytest.raises(EpisodeError, match="no such episode"):
        export_dataset(FIXTURES, tmp_path / "d", ["door_99"])
    assert not list(tmp_path.glob(".*partial"))  # nothing half-written left behind


def test_cli_export_and_one_line_errors(tmp_path, capsys):
    out = tmp_path / "ds"
    assert cli_main(["export-dataset", str(out), "--episodes", "door_01"]) == 0
    assert "1 episodes, " in capsys.readouterr().out
    assert cli_main(["export-dataset", str(out), "--episodes", "door_01"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vlmproprio: error:") and "--overwrite" in err and "\n" not in err
    assert cli_main(["export-dataset", str(FIXTURES / "ds"), "--episodes", "door_01"]) == 2
    assert "inside the fixture folder" in capsys.readouterr().err
