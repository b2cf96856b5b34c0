"""A backend kind is one module: a kind registered here, and declared nowhere else, is a model name, settings,
command-line options, a backend and an availability check."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import pytest

from vlmproprio import kinds, models
from vlmproprio.backends.base import Availability, Backend
from vlmproprio.backends.registry import KINDS, create_backend, format_availability, model_availability
from vlmproprio.backends.settings import BackendSettings
from vlmproprio.chat import Answer, AnswerMeta, ChatRequest
from vlmproprio.cli.backend_options import backend_settings
from vlmproprio.cli.parser import build_parser
from vlmproprio.kinds import KindError, KindOption, KindSpec, register_kind
from vlmproprio.models import ModelNameError, file_slug, resolve_model


@dataclass(frozen=True)
class ToySettings:
    loudness: int = 3


class ToyBackend(Backend):
    def __init__(self, word: str, loudness: int) -> None:
        self.word, self.loudness = word, loudness

    def identity(self) -> dict[str, str]:
        return {"backend": "toy", "model_id": self.word}

    def generate(self, requests: Sequence[ChatRequest]) -> list[Answer]:
        return [Answer(self.word * self.loudness, AnswerMeta("toy", self.word)) for _ in requests]


def _create(ref, settings: BackendSettings) -> Backend:
    return ToyBackend(ref.weights, settings.for_kind("toy").loudness)


def _live(ref, settings: BackendSettings) -> Availability:
    return Availability(settings.toy.loudness > 0, f"toy {ref.weights} at loudness {settings.toy.loudness}")


TOY = KindSpec(
    kind="toy",
    create=_create,
    live=_live,
    prefix="toy:",
    syntax="toy:<word>",
    label="a toy",
    slug=lambda name, weights: file_slug(name, "toy", weights, weights, lossless=True),
    settings_type=ToySettings,
    options=(KindOption("--loudness", "loudness", {"run": "how often the toy repeats its word (default 3)"}, int, 3),),
    option_group="toy models (toy)",
)


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch) -> KindSpec:
    kinds.kind_specs()  # the real kinds first, then a copy of the table the toy is added to and dropped from
    monkeypatch.setattr(kinds, "_REGISTERED", dict(kinds._REGISTERED))
    models._resolve.cache_clear()
    register_kind(TOY)
    yield TOY
    models._resolve.cache_clear()


def test_the_backend_modules_register_the_kinds() -> None:
    assert {"hf", "openai", "reference"} <= set(KINDS)
    assert KINDS["hf"].prefix == "hf:" and not KINDS["reference"].needs_cassette


def test_a_registered_kind_is_a_model_name(toy: KindSpec) -> None:
    ref = resolve_model("toy:quack")
    assert (ref.kind, ref.slug, ref.weights, ref.description) == ("toy", "toy_quack", "quack", "quack (a toy)")
    assert resolve_model("toy:Quack").slug.startswith("toy_Quack-")  # lossy: a digest tail, as for hf and openai
    with pytest.raises(ModelNameError, match=r"toy:<word>"):
        resolve_model("no-such-model")


def test_an_unregistered_kind_is_no_model_name() -> None:
    with pytest.raises(ModelNameError, match="unknown model"):
        resolve_model("toy:quack")


def test_a_kind_has_its_settings(toy: KindSpec) -> None:
    settings = BackendSettings.of(loudness=5, threads=1)
    assert settings.toy == ToySettings(5) and settings.hf.threads == 1
    assert BackendSettings().for_kind("toy") == ToySettings()
    assert settings.record()["loudness"] == 5


def test_a_kind_has_its_options(toy: KindSpec, capsys: pytest.CaptureFixture[str]) -> None:
    args = build_parser().parse_args(["run", "--model", "toy:quack", "--loudness", "7"])
    assert backend_settings(args).toy.loudness == 7
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "--help"])
    out = capsys.readouterr().out
    assert "toy models (toy):" in out and "how often the toy repeats its word (default 3)" in out


def test_a_kind_is_built_and_checked(toy: KindSpec, tmp_path) -> None:
    settings = BackendSettings.of(loudness=2, cassette_dir=tmp_path)
    assert model_availability("toy:quack", "live", settings) == Availability(True, "toy quack at loudness 2")
    assert not model_availability("toy:quack", "replay", settings)  # it needs a cassette, and has none
    assert not model_availability("toy:quack", "live", BackendSettings.of(loudness=0))
    with create_backend("toy:quack", "live", settings) as backend:
        assert backend.generate([ChatRequest(())])[0].text == "quackquack"
    assert "toy:quack  [toy: quack]  replay: no  live: yes" in format_availability(settings, ["toy:quack"])


def test_two_kinds_cannot_claim_one_prefix(toy: KindSpec) -> None:
    with pytest.raises(KindError, match="both claim prefix 'toy:'"):
        register_kind(KindSpec(kind="toy2", create=_create, live=_live, prefix="toy:"))
