"""Named episode sets (`vlmproprio record --set NAME --out DIR`): the extended set's plan (sizes, balance, seeds
that never meet the shipped episodes' or each other's), the per-episode digests a recording is checked against,
and what a differing, missing or extra episode says.

Recordings here are cut after a few steps of a small set put in place of the catalog's (``max_steps``): the
machinery is tested, not the operators; the whole extended set is checked by ``record --set extended`` itself."""

from __future__ import annotations

import importlib.util
import json
import shutil
from collections import Counter
from pathlib import Path

import pytest

from vlmproprio.errors import UsageError
from vlmproprio.record import named_sets
from vlmproprio.record.named_sets import NamedSet, Part, SetDigestError, check_digests, episode_digests, named_set

needs_robosuite = pytest.mark.skipif(
    importlib.util.find_spec("robosuite") is None,
    reason="recording needs the [record] extra (robosuite==1.5.2, mujoco==3.3.7): pip install -e .[record]",
)
STEPS = 25  # 2 frames an episode


def test_the_extended_set_is_216_balanced_episodes_on_seeds_no_one_else_uses():
    ext = named_set("extended")
    plans = ext.plans()
    assert Counter(p.family.task for p in plans) == {"door": 60, "pick_place": 96, "stack": 60}
    pick = [p for p in plans if p.family.task == "pick_place"]
    assert set(Counter((p.obj.name, p.bin_index) for p in pick).values()) == {6}  # 4 objects x 4 compartments x 6
    assert len(Counter((p.obj.name, p.bin_index) for p in pick)) == 16
    seeds = [s for p in plans for s in p.seeds]  # every seed a slot may try, retries included
    assert len(seeds) == len(set(seeds)) and min(seeds) > 11  # the shipped 22 use seeds 0-11
    assert len({p.episode_id for p in plans}) == 216


def test_the_extended_set_has_committed_digests_for_every_episode():
    doc = named_sets.committed_digests("extended")
    assert sorted(doc["episodes"]) == sorted(p.episode_id for p in named_set("extended").plans())
    assert all(len(d) == 64 for d in doc["episodes"].values())
    assert {"robosuite", "mujoco"} <= set(doc["versions"])


def test_unknown_set_and_conflicting_options_are_refused(capsys):
    from vlmproprio.cli import main

    with pytest.raises(UsageError, match=r"unknown episode set 'nope'.*known: extended"):
        named_set("nope")
    assert main(["record", "--set", "extended"]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["record", "--set", "extended", "--count", "3", "--out", "x"]) == 2
    assert "drop --task, --count" in capsys.readouterr().err
    assert main(["record", "--write-digests"]) == 2
    assert "goes with --set" in capsys.readouterr().err


def _fake_folder(root: Path, episodes: dict[str, dict[str, bytes]]) -> Path:
    from vlmproprio.episodes import write_manifest

    for ep, files in episodes.items():
        for rel, data in files.items():
            (root / "episodes" / ep / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / "episodes" / ep / rel).write_bytes(data)
    write_manifest(root)
    return root


def test_an_episode_digest_covers_its_files_and_their_names_only(tmp_path: Path):
    a = _fake_folder(tmp_path / "a", {"e1": {"episode.json": b"{}", "frames/000.png": b"x"}, "e2": {"x": b"1"}})
    b = _fake_folder(tmp_path / "b", {"e1": {"episode.json": b"{}", "frames/000.png": b"x"}, "e2": {"x": b"2"}})
    c = _fake_folder(tmp_path / "c", {"e1": {"episode.json": b"{}", "frames/001.png": b"x"}, "e2": {"x": b"1"}})
    da, db, dc = episode_digests(a), episode_digests(b), episode_digests(c)
    assert da["e1"] == db["e1"] and da["e2"] != db["e2"]  # one changed byte, one changed digest
    assert da["e1"] != dc["e1"] and da["e2"] == dc["e2"]  # a renamed frame changes it too


def test_a_differing_missing_or_extra_episode_is_named(tmp_path: Path, monkeypatch):
    root = _fake_folder(tmp_path / "set", {f"e{k}": {"episode.json": str(k).encode()} for k in range(4)})
    digests = tmp_path / "digests.json"
    committed = {**episode_digests(root), "e9": "0" * 64}
    committed["e1"] = "f" * 64
    digests.write_text(json.dumps({"version": 1, "set": "t", "versions": {"mujoco": "0"}, "episodes": committed}))
    monkeypatch.setattr(named_sets, "digests_path", lambda name: digests)
    shutil.rmtree(root / "episodes" / "e3")
    (root / "episodes" / "x1").mkdir()
    (root / "episodes" / "x1" / "episode.json").write_text("{}")
    (root / "recording.json").write_text(json.dumps({"versions": {"mujoco": "1"}}))
    from vlmproprio.episodes import write_manifest

    write_manifest(root)
    check = check_digests(root, "t")
    assert not check.ok and check.matching == 2
    assert (check.differing, check.missing, check.extra) == (("e1",), ("e3", "e9"), ("x1",))
    msg = check.message(root)
    assert "1 differing: e1" in msg and "2 missing: e3, e9" in msg and "1 not in the set: x1" in msg
    assert "rendering differs between versions" in msg


def test_missing_or_malformed_committed_digests_are_named(tmp_path: Path, monkeypatch):
    digests = tmp_path / "d.json"
    monkeypatch.setattr(named_sets, "digests_path", lambda name: digests)
    with pytest.raises(SetDigestError, match="no committed digests"):
        named_sets.committed_digests("t")
    digests.write_text("[1]")
    with pytest.raises(SetDigestError, match="malformed"):
        named_sets.committed_digests("t")


@pytest.fixture
def small_set(monkeypatch, tmp_path: Path) -> NamedSet:
    """A two-part set in place of the catalog's, its digests written into the test's own folder."""
    small = NamedSet("small", "", (Part("door", 1, 500), Part("stack", 2, 600)))
    monkeypatch.setattr(named_sets, "named_sets", lambda: {"small": small})
    monkeypatch.setattr(named_sets, "digests_path", lambda name: tmp_path / f"{name}.digests.json")
    return small


@needs_robosuite
@pytest.mark.record
@pytest.mark.slow
def test_a_named_set_records_its_parts_into_one_folder_and_is_checked_against_its_digests(
    small_set: NamedSet, tmp_path: Path, capsys
):
    from vlmproprio.episodes import load_episodes
    from vlmproprio.record.recorder import versions
    from vlmproprio.record.sets import record_plans, with_versions

    first = tmp_path / "first"
    # what record --set small --write-digests does, but cut short: digests of a cut set come from record_plans
    record_plans(small_set.plans(), first, with_versions(small_set.doc(), STEPS), max_steps=STEPS, progress=False)
    named_sets.write_digests(first, "small", versions())
    eps = load_episodes(first)
    assert [e.episode_id for e in eps] == ["door-s500-000", "stack-s600-000", "stack-s600-001"]
    assert json.loads((first / "recording.json").read_text())["set"] == "small"

    from vlmproprio.cli import main

    by_cli = tmp_path / "by_cli"  # the command line's way in, resumed to nothing the second time
    argv = ["record", "--set", "small", "--out", str(by_cli), "--max-steps", str(STEPS), "--no-progress"]
    assert main(argv) == 0
    assert "recorded 3 episodes" in capsys.readouterr().out
    assert main([*argv, "--workers", "2"]) == 0
    assert "recorded 0 episodes" in capsys.readouterr().out
    assert named_sets.episode_digests(by_cli) == named_sets.episode_digests(first)

    again = tmp_path / "again"
    record_plans(
        small_set.plans(), again, with_versions(small_set.doc(), STEPS), workers=2, max_steps=STEPS, progress=False
    )
    assert check_digests(again, "small").ok  # two workers, the same bits
    assert main(["verify", "--fixtures", str(again), "--set", "small"]) == 0
    assert "all 3 episodes match the committed digests" in capsys.readouterr().out
    digests = named_sets.digests_path("small")  # the set moved on: another episode where this one was
    doc = json.loads(digests.read_text())
    doc["episodes"]["stack-s600-001"] = "0" * 64
    digests.write_text(json.dumps(doc))
    assert main(["verify", "--fixtures", str(again), "--set", "small"]) != 0
    assert "1 differing: stack-s600-001" in capsys.readouterr().err
    assert named_sets.record_named("small", first, max_steps=STEPS, progress=False) is None
    assert "not checked against the committed digests" in capsys.readouterr().out
    with pytest.raises(UsageError, match="another episode set"):
        named_sets.record_named("small", first, progress=False)  # cut short there: not the whole set, not resumed
