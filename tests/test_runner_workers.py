"""Captioning split over forked workers where answers are pure (Answerer.pure: rules, a cassette's replay): the
same transcripts and statistics as one process, errors as one process raises them, and never a split of
answering that reads or fills a cache."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from vlmproprio import runner
from vlmproprio.cassettes import ReplayMissError
from vlmproprio.cli import main
from vlmproprio.conditions import parse_conditions
from vlmproprio.episodes import write_manifest
from vlmproprio.errors import UsageError
from vlmproprio.runner import RunPlan, run
from vlmproprio.transcripts import read_transcripts

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CONDITIONS = tuple(parse_conditions("none,both,both_shuffled"))


def _without_latency(doc):
    """A transcript's JSON without the backend's measured latencies (wall time, never the same twice)."""
    if isinstance(doc, dict):
        return {k: _without_latency(v) for k, v in doc.items() if k not in ("latency_s", "timing")}
    if isinstance(doc, list):
        return [_without_latency(v) for v in doc]
    return doc


def _files(run_dir: Path) -> dict[str, dict]:
    return {
        p.relative_to(run_dir).as_posix(): _without_latency(json.loads(p.read_text()))
        for p in sorted((run_dir / "transcripts").rglob("*.json"))
    }


def _run(tmp_path: Path, name: str, workers: int, fixtures: Path = FIXTURES, **kw):
    plan = RunPlan(
        models=("reference", "tiny-qwen2-vl"),
        conditions=CONDITIONS,
        fixtures=fixtures,
        out=tmp_path / name,
        mode="replay",
        progress=False,
        workers=workers,
        **kw,
    )
    return plan, run(plan)


@pytest.fixture
def splits(monkeypatch):
    """Per captioning: its worker count, its number of episodes, and how many of them this process captioned."""
    seen: list[dict] = []
    real = runner.map_groups

    def spy(fn, items, workers, group, **kw):
        seen.append({"workers": workers, "episodes": len(items)})

        def counted(part):
            seen[-1].setdefault("here", len(part))  # in a forked worker, this stays in the worker
            return fn(part)

        return real(counted, items, workers, group, **kw)

    monkeypatch.setattr(runner, "map_groups", spy)
    return seen


def test_transcripts_and_statistics_are_those_of_one_process(tmp_path, splits):
    _, one = _run(tmp_path, "one", 1)
    _, three = _run(tmp_path, "three", 3)
    assert [s["workers"] for s in splits] == [1, 1, 3, 3]  # per model
    assert [s["here"] for s in splits] == [22, 22, 8, 8]  # 22 episodes dealt in turn to 3 workers: 8, 7, 7
    assert [m.stats for m in three] == [m.stats for m in one]
    assert all(m.stats["misses"] > 0 for m in one)
    for a, b in zip(one, three, strict=True):  # returned in the same (episode-major) order
        assert [_without_latency(t.to_dict()) for t in a.transcripts] == [
            _without_latency(t.to_dict()) for t in b.transcripts
        ]
    files = _files(tmp_path / "one")
    assert len(files) == 2 * 22 * len(CONDITIONS) and files == _files(tmp_path / "three")
    read_back = read_transcripts(tmp_path / "three", "reference")
    assert len(read_back) == 22 * len(CONDITIONS)
    run_file = json.loads((tmp_path / "three" / "run.json").read_text())
    assert [m["stats"] for m in run_file["models"]] == [m.stats for m in one]


def test_a_set_larger_than_a_block_is_captioned_block_by_block_to_the_same_transcripts(tmp_path, splits, monkeypatch):
    """A set is read and captioned EPISODES_PER_BLOCK episodes at a time (memory bounded by a block, not the
    set): the transcripts, their files and the statistics are the same as in one block."""
    _, whole = _run(tmp_path, "whole", 2)
    monkeypatch.setattr(runner, "EPISODES_PER_BLOCK", 5)
    read = []
    real_images = runner.episode_images
    monkeypatch.setattr(runner, "episode_images", lambda eps: read.append(len(eps)) or real_images(eps))
    splits.clear()
    _, blocks = _run(tmp_path, "blocks", 2)
    assert read == [5, 5, 5, 5, 2] * 2  # per model: 22 episodes in blocks of 5, each block's images read once
    assert [s["episodes"] for s in splits] == [5, 5, 5, 5, 2] * 2
    assert [m.stats for m in blocks] == [m.stats for m in whole]
    for a, b in zip(whole, blocks, strict=True):
        assert [_without_latency(t.to_dict()) for t in a.transcripts] == [
            _without_latency(t.to_dict()) for t in b.transcripts
        ]
    assert _files(tmp_path / "blocks") == _files(tmp_path / "whole")


def test_answering_with_a_cache_is_never_split(tmp_path, splits):
    plan = RunPlan(
        models=("reference",),
        conditions=CONDITIONS[:1],
        fixtures=FIXTURES,
        out=tmp_path / "live",
        mode="live",
        cache_dir=tmp_path / "cache",
        progress=False,
        workers=4,
    )
    (done,) = run(plan)
    assert splits == [{"workers": 1, "episodes": 22, "here": 22}]
    assert done.stats["stored"] == done.stats["misses"] > 0  # live: the response cache is filled


def test_a_miss_in_a_workers_part_is_the_error_one_process_raises(tmp_path):
    ids = sorted(p.name for p in (FIXTURES / "episodes").iterdir())[:8]
    fixtures = tmp_path / "fx"
    for eid in ids:
        shutil.copytree(FIXTURES / "episodes" / eid, fixtures / "episodes" / eid)
    (fixtures / "responses").mkdir()
    lines = (FIXTURES / "responses" / "tiny-qwen2-vl.jsonl").read_text().splitlines(keepends=True)
    gone = ids[-1]  # dealt to a worker, not to this process (the episodes are dealt in turn)
    kept = [ln for ln in lines[1:] if json.loads(ln)["tag"]["episode_id"] != gone]
    assert len(kept) < len(lines) - 1
    (fixtures / "responses" / "tiny-qwen2-vl.jsonl").write_text(lines[0] + "".join(kept))
    write_manifest(fixtures)
    errors = []
    for workers in (1, 2):
        with pytest.raises(ReplayMissError) as info:
            run(
                RunPlan(
                    models=("tiny-qwen2-vl",),
                    conditions=CONDITIONS[:2],  # both_shuffled borrows from all 22 episodes: not in this subset
                    fixtures=fixtures,
                    out=tmp_path / f"w{workers}",
                    episode_ids=tuple(ids),
                    mode="replay",
                    progress=False,
                    workers=workers,
                )
            )
        errors.append((str(info.value), info.value.key))
        # the parts that were done are not written either: the folder is as one process leaves it
        folder = tmp_path / f"w{workers}"
        assert [p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()] == ["run.json"]
    assert errors[0] == errors[1] and gone in errors[0][0]


@pytest.mark.parametrize("bad", [0, -1, "two"])
def test_a_bad_worker_count_is_refused_before_any_work(tmp_path, bad, monkeypatch):
    with pytest.raises(UsageError, match="workers must be a whole number"):
        RunPlan(models=("reference",), conditions=CONDITIONS, fixtures=FIXTURES, out=tmp_path / "x", workers=bad)
    monkeypatch.setenv("VLMPROPRIO_WORKERS", str(bad))  # from the environment too, whichever models run
    with pytest.raises(UsageError, match=r"\$VLMPROPRIO_WORKERS must be a whole number"):
        RunPlan(models=("tiny-qwen2-vl",), conditions=CONDITIONS, fixtures=FIXTURES, out=tmp_path / "x", mode="live")
    assert not (tmp_path / "x").exists()


def test_without_progress_no_bar_is_built(tmp_path, monkeypatch):
    """Not even a disabled one: tqdm takes its class lock then, which a forked worker could inherit held."""
    import tqdm

    monkeypatch.setattr(tqdm, "tqdm", lambda *a, **k: pytest.fail("a progress bar was built"))
    _run(tmp_path, "quiet", 2)


def test_cli_run_takes_workers(tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["run", "--model", "reference", "--fixtures", str(FIXTURES), "--out", str(out), "--no-progress"]
    assert main([*argv, "--conditions", "none", "--mode", "replay", "--workers", "2"]) == 0
    assert len(list((out / "transcripts" / "reference").glob("*.json"))) == 22
    capsys.readouterr()
    assert main([*argv, "--workers", "zero"]) == 2
    assert "--workers must be a whole number" in capsys.readouterr().err
