"""One vocabulary: list syntax, mode default, ranges, --version, models availability, locations, summaries."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vlmproprio.cli import build_parser, main
from vlmproprio.errors import UsageError
from vlmproprio.locations import cache_root, resolve_fixtures
from vlmproprio.options import DEFAULT_MODE, split_list

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "fixtures"


def test_comma_lists_and_repeated_options_are_the_same() -> None:
    p = build_parser()
    a = p.parse_args(
        ["run", "--model", "reference,tiny-qwen2-vl", "--episodes", "door_00,bin0_00", "--conditions", "none,both"]
    )
    repeated = ["--model", "reference", "--model", "tiny-qwen2-vl", "--episodes", "door_00", "--episodes", "bin0_00"]
    b = p.parse_args(["run", *repeated, "--conditions", "none", "--conditions", "both"])
    for name in ("model", "episodes", "conditions"):
        assert split_list(getattr(a, name)) == split_list(getattr(b, name)), name
    assert split_list(["a, b", "c", "a"]) == ["a", "b", "c"]


def test_the_mode_default_is_the_same_in_the_cli_and_the_benchmark() -> None:
    from vlmproprio.pytest_plugin import OPTIONS

    assert build_parser().parse_args(["run", "--model", "reference"]).mode == DEFAULT_MODE == "auto"
    assert OPTIONS["mode"]["default"] == DEFAULT_MODE


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("vlmproprio ")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["score", "nowhere", "--threshold", "1.5"], "--threshold must be in [0, 1], got 1.5"),
        (["score", "nowhere", "--threshold", "-0.1"], "--threshold must be in [0, 1]"),
        (["score", "nowhere", "--encoder-batch-size", "0"], "--encoder-batch-size must be in [1, inf]"),
        (["run", "--model", "reference", "--batch-size", "0"], "--batch-size must be in [1, inf], got 0"),
        (["run", "--model", "reference", "--threads", "0"], "--threads must be in [1, inf]"),
    ],
)
def test_out_of_range_numbers_are_refused_in_one_line(argv, message, capsys) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_models_says_what_can_run_here(capsys) -> None:
    assert main(["models", "--fixtures", str(FIXTURES), "--model", "tiny-qwen2-vl,gpt-4o,reference"]) == 0
    out = capsys.readouterr().out
    assert "tiny-qwen2-vl  [hf: tiny:qwen2-vl]  replay: yes  live: yes" in out
    assert "gpt-4o  [openai: gpt-4o-2024-08-06]  replay: no" in out
    assert "vlmproprio run --model gpt-4o --mode record" in out  # how to get a cassette
    assert "reference  [reference]  replay: yes  live: yes" in out


def test_allow_download_is_off_by_default_and_says_why_it_failed(monkeypatch, capsys, tmp_path) -> None:
    from vlmproprio.backends.registry import BackendSettings, model_availability

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    off = model_availability("qwen2-vl", "live", BackendSettings())
    on = model_availability("qwen2-vl", "live", BackendSettings.of(allow_download=True))
    if off:
        pytest.skip("Qwen2-VL weights are in this machine's Hugging Face cache")
    assert "--allow-download" in off.reason
    assert on and "downloaded from the Hugging Face Hub" in on.reason
    args = ["run", "--model", "qwen2-vl", "--mode", "live", "--allow-download", "--fixtures", str(FIXTURES)]
    out = tmp_path / "never"  # a folder of the test's own: a real path outside it would outlive the test
    assert main([*args, "--episodes", "door_00", "--conditions", "none", "--out", str(out)]) == 2
    assert "--allow-download: could not download Qwen/Qwen2-VL-2B-Instruct" in capsys.readouterr().err
    assert not list(out.glob("transcripts/*/*.json"))  # nothing was captioned


def test_fixtures_come_from_the_option_then_the_environment_then_the_repository(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("VLMPROPRIO_FIXTURES", raising=False)
    monkeypatch.chdir(REPO / "docs")
    assert resolve_fixtures() == FIXTURES  # the repository the command runs in
    (tmp_path / "env").mkdir()
    (tmp_path / "opt").mkdir()
    monkeypatch.setenv("VLMPROPRIO_FIXTURES", str(tmp_path / "env"))
    assert resolve_fixtures() == tmp_path / "env"
    assert resolve_fixtures(tmp_path / "opt") == tmp_path / "opt"


def test_a_named_fixture_folder_that_is_not_there_is_an_error(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("VLMPROPRIO_FIXTURES", str(tmp_path / "env"))
    with pytest.raises(UsageError, match=r"\$VLMPROPRIO_FIXTURES .*env: does not exist"):
        resolve_fixtures()
    with pytest.raises(UsageError, match=r"--fixtures .*opt: does not exist"):
        resolve_fixtures(tmp_path / "opt")
    assert resolve_fixtures(tmp_path / "new", must_exist=False) == tmp_path / "new"  # record makes it


def test_outside_a_repository_and_a_checkout_the_error_says_how(monkeypatch, tmp_path) -> None:
    from vlmproprio import locations

    monkeypatch.delenv("VLMPROPRIO_FIXTURES", raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(locations, "_source_checkout_fixtures", lambda: None)  # as from an installed wheel
    with pytest.raises(UsageError, match="pass --fixtures DIR or set VLMPROPRIO_FIXTURES=DIR"):
        resolve_fixtures()


def test_caches_default_to_the_user_cache_directory(monkeypatch, tmp_path) -> None:
    import platformdirs

    monkeypatch.delenv("VLMPROPRIO_CACHE", raising=False)
    assert cache_root() == Path(platformdirs.user_cache_dir("vlmproprio", appauthor=False))
    monkeypatch.setenv("VLMPROPRIO_CACHE", str(tmp_path))
    assert cache_root() == tmp_path
    assert cache_root(tmp_path / "opt") == tmp_path / "opt"


def test_a_replayed_run_reports_no_model_calls(tmp_path, capsys) -> None:
    args = ["run", "--model", "tiny-qwen2-vl", "--fixtures", str(FIXTURES), "--episodes", "door_00"]
    assert main([*args, "--conditions", "none", "--out", str(tmp_path / "r"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "(replay)" in out and "answers replayed from the cassette, 0 model calls" in out
    assert "model calls" not in out.replace("0 model calls", "")
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    assert run["mode"] == "auto" and run["models"][0]["mode"] == "replay"
