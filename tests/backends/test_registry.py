"""Model names, slugs, backend creation and availability."""

from __future__ import annotations

import pytest

from vlmproprio.backends.base import BackendError
from vlmproprio.backends.registry import BackendSettings, create_backend, model_availability
from vlmproprio.cassettes import write_cassette
from vlmproprio.errors import VlmproprioError
from vlmproprio.models import REGISTRY, ModelNameError, format_registry, resolve_model


def test_registry_has_the_models_the_paper_and_ci_need():
    expect = {
        "qwen2-vl": ("hf", "Qwen/Qwen2-VL-2B-Instruct"),
        "qwen2-vl-7b": ("hf", "Qwen/Qwen2-VL-7B-Instruct"),
        "qwen2.5-vl": ("hf", "Qwen/Qwen2.5-VL-3B-Instruct"),
        "llava": ("hf", "llava-hf/llava-1.5-7b-hf"),
        "gpt-4v": ("openai", "gpt-4-vision-preview"),
        "gpt-4o": ("openai", "gpt-4o-2024-08-06"),  # a snapshot: the alias moves
        "tiny-qwen2-vl": ("hf", "tiny:qwen2-vl"),
        "tiny-qwen2.5-vl": ("hf", "tiny:qwen2.5-vl"),
        "tiny-llava": ("hf", "tiny:llava"),
        "reference": ("reference", ""),
        "reference-state": ("reference", "state-aware rules, NOT a VLM"),
    }
    for name, (backend, weights) in expect.items():
        assert (REGISTRY[name].kind, REGISTRY[name].weights) == (backend, weights)
    table = format_registry().splitlines()
    assert table[0].split() == ["name", "backend", "default", "weights"] and len(table) == len(REGISTRY) + 1


@pytest.mark.parametrize(
    ("name", "slug"),
    [
        ("qwen2.5-vl", "qwen2.5-vl"),
        ("gpt-4v", "gpt-4v"),
        ("hf:Qwen/Qwen2-VL-2B-Instruct", "hf_Qwen_Qwen2-VL-2B-Instruct-f3c975da"),
        ("hf:/data/models/my ckpt/", "hf_my_ckpt-05c69157"),
        ("hf:./tiny", "hf_tiny-3db8843a"),
        ("openai:gpt-4o-mini", "openai_gpt-4o-mini"),
        ("openai:meta-llama/Llama-3.2-11B-Vision", "openai_meta-llama_Llama-3.2-11B-Vision-2e6296c9"),
    ],
)
def test_slugs_are_single_safe_components(name, slug, tmp_path):
    assert resolve_model(name).slug == slug
    path = resolve_model(name).cassette(tmp_path)
    assert path.parent == tmp_path and path.name == slug + ".jsonl"


@pytest.mark.parametrize(
    "name",
    ["../etc/passwd", "hf:../../x", "openai:a/../../b", "gpt\x00-4v", "hf:", "openai:/", "hf:...", "a\\b", "", " "],
)
def test_unsafe_names_are_refused(name):
    with pytest.raises(ModelNameError):
        resolve_model(name)


# Pairs of different models whose readable names sanitise alike (issue 15, defect 2).
COLLIDING = [
    ("openai:org/m", "openai:org_m"),
    ("hf:/ckpt/run1/checkpoint-500", "hf:/ckpt/run2/checkpoint-500"),
    ("hf:org/name", "hf:org_name"),
    ("openai:GPT-4o", "openai:gpt-4o"),  # one folder on a case-insensitive disk
    ("openai:a b", "openai:a_b"),
    ("openai:org_m-9e955f65", "openai:org/m"),  # a name that looks like another's digest suffix
    ("hf:./tiny", "hf:/x/tiny"),
]


@pytest.mark.parametrize(("a", "b"), COLLIDING)
def test_models_whose_names_sanitise_alike_get_different_folders(a, b):
    sa, sb = resolve_model(a).slug, resolve_model(b).slug
    assert sa != sb and sa.lower() != sb.lower()


def test_model_names_with_line_separators_are_refused():
    for name in ("openai:gpt\u2028-4o", "openai:gpt\u2029x", "hf:a\u200bb"):
        with pytest.raises(ModelNameError, match="unprintable"):
            resolve_model(name)


def test_unknown_name_lists_the_registry():
    with pytest.raises(ModelNameError) as info:
        resolve_model("gpt-5-vision")
    msg = str(info.value)
    assert all(n in msg for n in REGISTRY) and "hf:<folder or HF repo id>" in msg
    assert isinstance(info.value, VlmproprioError)  # the CLI prints it as one line


def test_reference_runs_in_every_mode():
    for mode in ("live", "record", "replay"):
        assert create_backend("reference", mode).identity()["backend"] == "reference"
        assert model_availability("reference", mode).available


def test_replay_needs_a_cassette_and_says_how_to_record(tmp_path):
    settings = BackendSettings(cassette_dir=tmp_path)
    avail = model_availability("gpt-4v", "replay", settings)
    assert not avail and "no cassette" in avail.reason and "--mode record" in avail.reason
    with pytest.raises(BackendError, match=r"no cassette for model 'gpt-4v'.*cassette export --model gpt-4v"):
        create_backend("gpt-4v", "replay", settings)
    identity = {"backend": "openai", "model_id": "gpt-4-vision-preview"}
    write_cassette(resolve_model("gpt-4v").cassette(tmp_path), "gpt-4v", identity, [])
    assert model_availability("gpt-4v", "replay", settings)
    backend = create_backend("gpt-4v", "replay", settings)
    assert backend.identity()["model_id"] == "gpt-4-vision-preview" and not backend.calls_model
    assert backend.model == "gpt-4v"


def test_live_availability_reasons(monkeypatch, tmp_path):
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    avail = model_availability("gpt-4o", "live")
    assert not avail and "$OPENAI_API_KEY" in avail.reason
    monkeypatch.setenv("OPENAI_API_KEY", "sk-x")
    assert model_availability("gpt-4o", "live")
    assert model_availability("openai:whatever", "live", BackendSettings.of(base_url="http://127.0.0.1:8000/v1"))
    pytest.importorskip("transformers")
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "empty-hub"))
    avail = model_availability("qwen2-vl", "live")
    assert not avail and "hf download Qwen/Qwen2-VL-2B-Instruct" in avail.reason
    assert model_availability("tiny-qwen2-vl", "live")


def test_unknown_mode_is_refused():
    with pytest.raises(VlmproprioError, match="unknown mode"):
        create_backend("reference", "turbo")
