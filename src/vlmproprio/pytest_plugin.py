"""pytest plugin: the benchmark as pytest tests. Inert unless asked for.

Installing vlmproprio adds nothing to other projects' pytest sessions: there is no ``pytest11`` entry point.
The repository's root ``conftest.py`` loads this module and adds the short option names, so in the repository
``pytest benchmark/ --model qwen2-vl`` runs the benchmark; elsewhere ``pytest -p vlmproprio.pytest_plugin``
loads it with the namespaced names (``--vlmproprio-model`` ...). Options (the CLI's vocabulary,
vlmproprio.options):

* ``--model NAME`` (comma list or repeated; default ``reference`` and ``tiny-qwen2-vl``), ``--conditions``,
  ``--episodes``, ``--mode auto|replay|live|record`` (default auto: a model's committed cassette when there
  is one, so CPU only), ``--run-dir`` (keep the run, its scores and embeddings), ``--fixtures-dir`` (pytest
  owns ``--fixtures``; default as the CLI's ``--fixtures``).
* Tests that take the ``bench_cell`` fixture are parametrised per (model, episode, condition), with ids
  like ``reference-door_03-both``, so ``-k door_03`` or ``-k both`` select cells and a failure names one.
* Each model is run once per session, lazily, for exactly the episodes and conditions of the cells
  selected, then scored. A model named with ``--model`` that cannot run here (no cassette, no weights, no
  server) stops the session before collection with one line: the reason and how to get it (exit code 4); a
  default model that cannot run is skipped with that reason. ``reference`` and ``tiny-qwen2-vl`` need nothing
  and always run.

Kept import-light: collecting tests/ with the benchmark's conftest in view must not import torch.
Session state lives in ``config.stash``.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from vlmproprio import options as opt
from vlmproprio.errors import one_line
from vlmproprio.locations import FIXTURES_ENV

if TYPE_CHECKING:  # annotations only: the work is in vlmproprio.bench, imported when a model runs
    from vlmproprio.bench import ModelResult
    from vlmproprio.models import ModelRef

DEFAULT_MODELS = ("reference", "reference-state", "tiny-qwen2-vl")
CELL_FIXTURE = "bench_cell"
MODEL_FIXTURE = "bench_model"


# Long, namespaced names only: the plugin may be loaded into sessions that define short options of their own.
# the repository's conftest.py adds the short spellings of the documented command `pytest benchmark/ --model NAME`.
OPTIONS: dict[str, dict] = {
    "model": dict(action="append", metavar="NAME", help=f"{opt.MODEL_HELP}; default: {', '.join(DEFAULT_MODELS)}"),
    "conditions": dict(action="append", metavar="CONDS", help=opt.CONDITIONS_HELP),
    "episodes": dict(action="append", metavar="IDS", help=opt.EPISODES_HELP),
    "mode": dict(default=opt.DEFAULT_MODE, choices=opt.MODES, help=opt.MODE_HELP),
    "run-dir": dict(default=None, metavar="DIR", help="keep runs, scores and reports here (default: a temp folder)"),
    # pytest itself owns --fixtures (it lists test fixtures): the benchmark's fixture folder is --fixtures-dir
    "fixtures-dir": dict(default=None, metavar="DIR", help=opt.FIXTURES_HELP),
}
SHORT_ALIASES = {"fixtures-dir": ("--bench-fixtures",)}
BENCH_KEY = pytest.StashKey["BenchSession"]()


def dest(name: str) -> str:
    return "vlmproprio_" + name.replace("-", "_")


def add_options(parser: pytest.Parser, *, short: bool) -> None:
    """The benchmark's options: ``--vlmproprio-<name>``, or with ``short`` (the conftest) ``--<name>``.

    Both spellings share one destination, so they can be mixed."""
    g = parser.getgroup("vlmproprio", "vlmproprio benchmark")
    for name, kwargs in OPTIONS.items():
        names = [f"--{name}", *SHORT_ALIASES.get(name, ())] if short else [f"--vlmproprio-{name}"]
        g.addoption(*names, dest=dest(name), **kwargs)


def pytest_addoption(parser: pytest.Parser) -> None:
    add_options(parser, short=False)


def option(config: pytest.Config, name: str):
    return config.getoption(dest(name))


def pytest_configure(config: pytest.Config) -> None:
    for name in ("run-dir", "fixtures-dir"):  # `--run-dir ""` (an empty shell variable) is not "the default"
        value = option(config, name)
        if value is not None and not str(value).strip():
            raise pytest.UsageError(f"--{name}: an empty path; give a folder, or leave the option out")
    # A wrong --model / --episodes / --conditions / --fixtures-dir is a usage error before collection (one clean
    # line), but only when given.
    if (
        option(config, "model")
        or option(config, "episodes") is not None
        or option(config, "conditions")
        or option(config, "fixtures-dir")
    ):
        try:
            _refuse_a_path_pytest_took_for_a_test_path(config)
            session = _session(config)
            if option(config, "model") and not config.option.collectonly:  # listing the cells runs none
                _refuse_unrunnable(session)
        except pytest.UsageError as exc:  # one line, as the CLI's: a name with a newline cannot split it
            raise pytest.UsageError(one_line(str(exc))) from None


def _refuse_a_path_pytest_took_for_a_test_path(config: pytest.Config) -> None:
    """``--fixtures-dir PATH`` with a space: pytest picks its rootdir and config file before it knows this
    plugin's options, so it took PATH for a test path, and a fixture folder in another clone made that clone's
    pyproject.toml the session's configuration. The choice cannot be undone here, so it is refused when it
    differs from the one the real test paths give; ``--fixtures-dir=PATH`` is read right."""
    spellings = {"--vlmproprio-fixtures-dir", "--fixtures-dir", *SHORT_ALIASES["fixtures-dir"]}
    given = list(config.invocation_params.args)
    used = next((a for a in given[:-1] if a in spellings), None)
    if used is None:
        return
    try:  # pytest's own rule for the choice (a private function: skip the check where it moved)
        from _pytest.config.findpaths import determine_setup

        rootpath, inipath, *_ = determine_setup(
            inifile=config.option.inifilename,
            override_ini=config.option.override_ini,
            args=[str(a) for a in config.args],
            rootdir_cmd_arg=config.option.rootdir or None,
            invocation_dir=config.invocation_params.dir,
        )
    except (ImportError, TypeError):
        return
    if (rootpath, inipath) != (config.rootpath, config.inipath):
        value = given[given.index(used) + 1]
        raise pytest.UsageError(
            f"{used} {value}: pytest took {value} for a test path when it chose its configuration "
            f"({config.inipath or config.rootpath}); write {used}={value}"
        )


def _refuse_unrunnable(session: BenchSession) -> None:
    """Models asked for by name that cannot run here stop the session once, before collection, with one line
    each: failing every cell of such a model would repeat the same reason hundreds of times."""
    reasons = []
    for model in session.models:
        avail = session.availability(model)
        if not avail:
            reasons.append(f"{model} cannot run in {session.mode} mode here: {avail.reason}")
    if reasons:
        from vlmproprio.secrets import scrub

        raise pytest.UsageError(scrub("; ".join(reasons)))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """``-n auto`` (the project's pytest default) runs in one process when the benchmark runs a model or keeps its
    run (each xdist worker runs the models it needs, so workers would record the same cassette or fill the same
    run folder at once), and when only the benchmark's folder is run (each worker would replay and score the
    models again, which costs more than spreading the cells saves). Otherwise None leaves it to xdist."""
    if option(config, "mode") not in ("replay", "auto") or option(config, "run-dir"):
        return 0
    bench = (Path(config.rootpath) / "benchmark").resolve()
    paths = [Path(str(a).split("::")[0]).resolve() for a in config.args]
    if paths and all(p == bench or bench in p.parents for p in paths):
        return 0
    return None


@dataclass(frozen=True)
class CellId:
    model: ModelRef
    episode_id: str
    condition: str

    def __str__(self) -> str:
        return f"{self.model}-{self.episode_id}-{self.condition}"


@dataclass
class BenchSession:
    """What the session's selected benchmark tests need, and the runs made for them (once per model)."""

    config: pytest.Config
    fixtures: Path
    mode: str
    run_root: Path | None  # None: a temporary folder made on first use
    models: tuple[ModelRef, ...]
    conditions: tuple[str, ...]
    episodes: tuple[str, ...]
    needed: dict[ModelRef, tuple[set[str], set[str]]] = field(default_factory=dict)
    results: dict[ModelRef, ModelResult] = field(default_factory=dict)
    failures: dict[ModelRef, str] = field(default_factory=dict)
    shared: Path | None = None  # the run folder the xdist workers share (see _shared_run_root)

    def need(self, model: ModelRef, episodes, conditions) -> None:
        eps, conds = self.needed.setdefault(model, (set(), set()))
        eps.update(episodes)
        conds.update(conditions)

    def availability(self, model: ModelRef):
        from vlmproprio.bench import availability

        return availability(model, self.mode, self.fixtures)

    def result(self, model: ModelRef, tmp_path_factory: pytest.TempPathFactory) -> ModelResult:
        if model in self.failures:
            pytest.fail(self.failures[model], pytrace=False)
        if self.run_root is None:
            self.shared = _shared_run_root(self.config, tmp_path_factory)
            self.run_root = self.shared or tmp_path_factory.mktemp("vlmproprio-bench")
        if model not in self.results:
            try:
                self.results[model] = self._run(model)
            except Exception as exc:
                from vlmproprio.errors import VlmproprioError

                if not isinstance(exc, VlmproprioError):
                    raise
                from vlmproprio.secrets import scrub

                self.failures[model] = scrub(f"{model}: {exc}")
                pytest.fail(self.failures[model], pytrace=False)
        return self.results[model]

    def _run(self, model: ModelRef) -> ModelResult:
        from vlmproprio.bench import run_and_score

        eps, conds = self.needed.get(model, (set(self.episodes), set(self.conditions)))
        assert self.run_root is not None
        conditions = [c for c in self.conditions if c in conds]  # the session's order
        run_root = self.run_root
        if self.shared is None:
            return run_and_score(model, self.fixtures, self.mode, eps, conditions, run_root)
        selection = json.dumps([sorted(eps), conditions, self.mode, str(self.fixtures)])
        # one lock per model (its runs share run_root/<slug>), one result per selection of cells
        lock = run_root / f"{model.slug}.lock"
        done = run_root / f"{model.slug}-{hashlib.sha256(selection.encode()).hexdigest()[:12]}.json"
        return _once_per_session(
            lock, done, lambda: run_and_score(model, self.fixtures, self.mode, eps, conditions, run_root)
        )


def _shared_run_root(config: pytest.Config, tmp_path_factory: pytest.TempPathFactory) -> Path | None:
    """Under pytest-xdist, one temporary run folder for all the session's workers (their base temp folders'
    common parent), so that a model is run and scored once per session, not once per worker that has benchmark
    tests (test_benchmark.py and test_claims.py land on different workers); None outside xdist."""
    if not hasattr(config, "workerinput"):  # what pytest-xdist gives a worker's config
        return None
    root = tmp_path_factory.getbasetemp().parent / "vlmproprio-bench"
    root.mkdir(parents=True, exist_ok=True)
    return root


def _once_per_session(lock: Path, done: Path, compute: Callable[[], ModelResult]) -> ModelResult:
    """``compute()`` once per session whichever worker gets here first; every worker, that one included, gets
    the result back from its JSON in ``done``, so all of them hold the same values."""
    from vlmproprio.bench import ModelResult
    from vlmproprio.io import text_computed_once

    return ModelResult.from_json(text_computed_once(lock, done, lambda: compute().to_json()))


def _session(config: pytest.Config) -> BenchSession:
    existing = config.stash.get(BENCH_KEY, None)
    if existing is not None:
        return existing
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import list_episode_ids
    from vlmproprio.errors import VlmproprioError, did_you_mean
    from vlmproprio.locations import find_repository_fixtures, resolve_fixtures

    explicit = option(config, "fixtures-dir")
    if explicit is None and not os.environ.get(FIXTURES_ENV):
        # the repository pytest runs in: `pytest /path/to/repo/benchmark` finds its fixtures from any folder
        explicit = find_repository_fixtures(Path(config.rootpath))
    try:
        fixtures = resolve_fixtures(explicit, flag="--fixtures-dir")
    except VlmproprioError as exc:
        message = str(exc)
        raise pytest.UsageError(
            message if message.startswith("--fixtures-dir") else f"--fixtures-dir: {message}"
        ) from None
    episodes_opt = option(config, "episodes")
    episodes = tuple(opt.split_list(episodes_opt))
    if episodes_opt is not None and not episodes:  # `--episodes ""` (an empty shell variable) is not "all"
        raise pytest.UsageError("--episodes: no episode ids given; name some (comma separated) or leave it out for all")
    if not episodes:
        episodes = tuple(list_episode_ids(fixtures))
    if not episodes:  # no cells to parametrise: pytest would crash (INTERNALERROR) on the empty parameter list
        raise pytest.UsageError(f"--fixtures-dir: no episodes in {fixtures / 'episodes'}; point it at a fixture folder")
    known = set(list_episode_ids(fixtures))
    unknown = [e for e in episodes if e not in known]
    if unknown:
        raise pytest.UsageError(
            f"--episodes: unknown episode(s) {', '.join(unknown)}{did_you_mean(unknown[0], known)} in {fixtures} "
            f"(known: {', '.join(sorted(known))})"
        )
    from vlmproprio.models import resolve_model

    try:
        models = tuple(map(resolve_model, opt.split_list(option(config, "model")) or DEFAULT_MODELS))
        conditions = tuple(c.name for c in parse_conditions(option(config, "conditions") or opt.DEFAULT_CONDITIONS))
    except VlmproprioError as exc:
        raise pytest.UsageError(str(exc)) from None
    run_dir = option(config, "run-dir")
    session = BenchSession(
        config=config,
        fixtures=fixtures,
        mode=option(config, "mode"),
        run_root=Path(run_dir) if run_dir else None,
        models=models,
        conditions=conditions,
        episodes=episodes,
    )
    config.stash[BENCH_KEY] = session
    return session


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if CELL_FIXTURE in metafunc.fixturenames:
        s = _session(metafunc.config)
        cells = [CellId(m, e, c) for m in s.models for e in s.episodes for c in s.conditions]
        metafunc.parametrize(CELL_FIXTURE, cells, ids=[str(c) for c in cells], indirect=True)
    elif MODEL_FIXTURE in metafunc.fixturenames:
        s = _session(metafunc.config)
        metafunc.parametrize(MODEL_FIXTURE, list(s.models), ids=[m.name for m in s.models], indirect=True)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """Record which cells survived -k / deselection, so each model runs exactly what is needed."""
    bench = config.stash.get(BENCH_KEY, None)
    if bench is None:
        return
    for item in items:
        callspec = getattr(item, "callspec", None)
        if callspec is None:
            continue
        if CELL_FIXTURE in callspec.params:
            cell: CellId = callspec.params[CELL_FIXTURE]
            bench.need(cell.model, [cell.episode_id], [cell.condition])
        elif MODEL_FIXTURE in callspec.params:
            # whole-model tests (the science gates) need every selected episode and condition
            bench.need(callspec.params[MODEL_FIXTURE], bench.episodes, bench.conditions)


def _skip_unavailable(s: BenchSession, model: ModelRef) -> None:
    avail = s.availability(model)
    if not avail:
        message = f"{model} cannot run in {s.mode} mode here: {avail.reason}"
        if option(s.config, "model"):
            # asked for by name: a benchmark of a model that cannot run is a failure, not "all skipped", exit 0
            pytest.fail(message, pytrace=False)
        pytest.skip(message)


@dataclass(frozen=True)
class CellResult:
    cell: CellId
    row: dict
    sweep: list[dict]
    run_dir: Path


@pytest.fixture
def bench_cell(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> CellResult:
    """The scored result of one (model, episode, condition) cell of the benchmark."""
    s = _session(request.config)
    cell: CellId = request.param
    _skip_unavailable(s, cell.model)
    res = s.result(cell.model, tmp_path_factory)
    key = (cell.episode_id, cell.condition)
    if key not in res.rows:
        pytest.fail(f"{cell}: the run produced no transcript for this cell", pytrace=False)
    return CellResult(cell, res.rows[key], res.sweep.get(key, []), res.run_dir)


@pytest.fixture
def bench_model(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> ModelResult:
    """A model's whole scored run (every selected episode and condition)."""
    s = _session(request.config)
    _skip_unavailable(s, request.param)
    return s.result(request.param, tmp_path_factory)


@pytest.fixture(scope="session")
def bench_session(request: pytest.FixtureRequest) -> BenchSession:
    return _session(request.config)
