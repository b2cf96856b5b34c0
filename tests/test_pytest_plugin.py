"""The benchmark's pytest plugin is inert unless asked for: another project's pytest is unchanged."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import tomllib

pytest_plugins = ("pytester",)

REPO = Path(__file__).resolve().parents[1]
# blocks the entry point an older editable install of vlmproprio may still declare (it would load the plugin a
# second time); a no-op where there is none
NO_STALE = ("-p", "no:vlmproprio")

OTHER_CONFTEST = """
def pytest_addoption(parser):
    parser.addoption("--model", default="theirs")
    parser.addoption("--mode", default="fast")
    parser.addoption("--episodes", default="")
    parser.addoption("--conditions", default="")
    parser.addoption("--run-dir", default="")
"""
OTHER_TEST = """
def test_their_options(request):
    assert request.config.getoption("--model") == "mine"
    assert request.config.getoption("--mode") == "fast"
"""


def test_another_project_defining_model_runs_green(pytester: pytest.Pytester) -> None:
    """A project whose conftest defines --model, --mode ... in an environment where vlmproprio is installed."""
    pytester.makeconftest(OTHER_CONFTEST)
    pytester.makepyfile(test_theirs=OTHER_TEST)
    result = pytester.runpytest_subprocess("--model", "mine", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)


def test_the_plugin_loaded_by_hand_uses_namespaced_names_only(pytester: pytest.Pytester) -> None:
    pytester.makeconftest(OTHER_CONFTEST)
    pytester.makepyfile(test_theirs=OTHER_TEST)
    result = pytester.runpytest_subprocess(*NO_STALE, "-p", "vlmproprio.pytest_plugin", "--model", "mine", "--help")
    assert result.ret == 0
    assert "--vlmproprio-model" in result.stdout.str()
    result = pytester.runpytest_subprocess(
        *NO_STALE, "-p", "vlmproprio.pytest_plugin", "--model", "mine", "-p", "no:cacheprovider"
    )
    result.assert_outcomes(passed=1)


def test_the_package_declares_no_pytest_entry_point() -> None:
    """An entry point would load the plugin into every pytest session of the environment."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert "pytest11" not in project.get("entry-points", {})


def test_the_benchmark_keeps_its_short_options() -> None:
    """`pytest benchmark/ --model NAME ...` as documented: the short names come from the root conftest.py."""
    import subprocess

    proc = subprocess.run(
        [sys.executable, "-m", "pytest", str(REPO / "benchmark"), "--help", "-p", "no:cacheprovider"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    for option in (
        "--model=NAME",
        "--mode=",
        "--episodes=IDS",
        "--conditions=CONDS",
        "--run-dir=DIR",
        "--fixtures-dir",
    ):
        assert option in proc.stdout, option


def test_plugin_state_lives_in_the_config_stash(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        test_stash="""
from vlmproprio import pytest_plugin

def test_stash(request):
    session = request.config.stash[pytest_plugin.BENCH_KEY]
    assert [m.name for m in session.models] == ["reference"]
    assert session.episodes == ("door_00", "bin0_00")
    assert not hasattr(request.config, "_vlmproprio_bench")
"""
    )
    result = pytester.runpytest_subprocess(
        *NO_STALE,
        "-p",
        "vlmproprio.pytest_plugin",
        "--vlmproprio-model",
        "reference",
        "--vlmproprio-episodes",
        "door_00",
        "--vlmproprio-episodes",
        "bin0_00",
        f"--vlmproprio-fixtures-dir={REPO / 'fixtures'}",  # with a space it would choose the configuration
        "-p",
        "no:cacheprovider",
    )
    result.assert_outcomes(passed=1)


def _root_conftest():
    """The repository's conftest.py as its own module (pytest has it loaded under a name of its own)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_vlmproprio_root_conftest", REPO / "conftest.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(args: list[Path], **options):
    from types import SimpleNamespace

    from vlmproprio.pytest_plugin import dest

    values = {dest("mode"): "auto", dest("run-dir"): None} | {dest(k.replace("_", "-")): v for k, v in options.items()}
    return SimpleNamespace(getoption=values.__getitem__, rootpath=REPO, args=[str(a) for a in args])


@pytest.mark.parametrize(
    ("args", "options", "one_process"),
    [
        ([REPO / "benchmark"], {}, True),  # the benchmark alone: the workers would each replay and score again
        ([REPO / "benchmark" / "test_claims.py"], {"mode": "replay"}, True),
        ([REPO / "tests", REPO / "benchmark"], {"mode": "record"}, True),  # workers would record one cassette
        ([REPO / "tests", REPO / "benchmark"], {"run_dir": "runs/x"}, True),
        ([REPO / "tests", REPO / "benchmark"], {}, False),  # the README's test command: spread over the cores
        ([REPO / "tests" / "test_stats.py"], {"mode": "replay"}, False),
    ],
)
def test_auto_workers_follow_the_plugin_where_it_decides(args, options, one_process) -> None:
    """`-n auto` asks the root conftest, whose answer xdist takes first: it must defer to the plugin's one-process
    rule (it once did not, and `pytest benchmark/` started a worker per core that each scored every model)."""
    import os

    workers = _root_conftest().pytest_xdist_auto_num_workers(_config(args, **options))
    assert workers == (0 if one_process else (os.cpu_count() or 1) + 1)


def _pytest_in(folder: Path, *args: str):
    import subprocess

    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", *args]
    return subprocess.run(cmd, cwd=folder, capture_output=True, text=True, timeout=300, check=False)


def test_a_fixture_folder_given_with_a_space_cannot_choose_the_configuration(tmp_path: Path) -> None:
    """With a space, pytest reads the folder as a test path while choosing its rootdir and config file, before
    it knows the plugin's options: a folder in a clone made the clone's pyproject.toml the configuration."""
    (tmp_path / "test_theirs.py").write_text("def test_theirs():\n    pass\n")
    fixtures = str(REPO / "fixtures")
    spaced = _pytest_in(tmp_path, "-p", "vlmproprio.pytest_plugin", "--vlmproprio-fixtures-dir", fixtures)
    assert spaced.returncode == 4, spaced.stdout + spaced.stderr
    assert f"write --vlmproprio-fixtures-dir={fixtures}" in spaced.stderr
    joined = _pytest_in(tmp_path, "-p", "vlmproprio.pytest_plugin", f"--vlmproprio-fixtures-dir={fixtures}")
    assert joined.returncode == 0, joined.stdout + joined.stderr
    # where the space changes nothing (the benchmark's own folder is a test path too), it is accepted
    inside = _pytest_in(tmp_path, str(REPO / "benchmark"), "--fixtures-dir", fixtures, "--collect-only")
    assert inside.returncode == 0, inside.stdout[-2000:] + inside.stderr[-2000:]
