"""Every tiny family end to end through the hf backend: one Door episode live (Process 1 with five images per
request, Process 2, Process 3 with all 31 frames), recorded as a cassette, replayed, and the replay's
transcripts and scores equal the live run's bit for bit."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest

from scoring_helpers import fake_spec, prefill_embeddings
from vlmproprio.backends.tiny import FAMILIES
from vlmproprio.cassettes import read_cassette
from vlmproprio.conditions import parse_conditions
from vlmproprio.episodes import load_episode
from vlmproprio.episodes.manifest import write_manifest
from vlmproprio.pipeline import calls_per_episode
from vlmproprio.runner import RunPlan, run
from vlmproprio.transcripts import read_transcripts

# checked, not imported: every xdist worker collects this module, and only the one that runs it needs transformers
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("transformers") is None, reason="the hf backend needs the [hf] extra"
)

ROOT = Path(__file__).resolve().parents[2]
EPISODE = "door_00"
# the families the tiny builds had before this module (test_hf and test_live_tiny run them)
EARLIER = ("qwen2-vl", "qwen2.5-vl", "llava")
# Image tokens one 256x256 frame costs in each family's published processor, placeholders excluded (the tiny
# builds keep it; LLaVA-OneVision's tiny tower has 48 px patches, 64 tokens a view where the real one has 729)
FRAME_TOKENS = {
    "qwen3-vl": 64,
    "gemma3": 256,
    "idefics3": 64,
    "internvl": 256,
    "llava-onevision": 65,
    "mistral3": 100,  # 256 px rounded up to 280 by the image processor
    "glm4v": 81,
    "mllama": 1,  # cross-attention: the frame is one <|image|> token in the text
    "idefics2": 64,  # one 378 px view resampled to 64 latents (image splitting off: published, five views)
    "llava-next": 136,  # base view and two anyres tiles at 42 px patches (the real 14 px: 1,176)
    "smolvlm": 64,  # as Idefics3: one 512 px view (image splitting off)
}
# Families whose processor transformers ships only with torchvision (PixtralProcessor): without it, their policy is
# a one-line error naming the model, the family and the fix
NEEDS_TORCHVISION = {"mistral3"}
NEW_FAMILIES = [f for f in FAMILIES if f not in EARLIER]


@pytest.fixture
def door_fixtures(tmp_path: Path) -> Path:
    """A fixture folder of one Door episode, whose responses/ the recording writes into."""
    dest = tmp_path / "fixtures"
    shutil.copytree(ROOT / "fixtures" / "episodes" / EPISODE, dest / "episodes" / EPISODE)
    write_manifest(dest)
    return dest


def _unrunnable(family: str) -> bool:
    from transformers.utils import is_torchvision_available

    return family in NEEDS_TORCHVISION and not is_torchvision_available()


def _refused(family: str, call) -> None:
    """Without torchvision, ``call`` refuses with one line that names the family and the fix."""
    from vlmproprio.backends.base import BackendError

    with pytest.raises(BackendError) as caught:
        call()
    message = str(caught.value)
    assert "\n" not in message and f"family {family.replace('-', '_')}" in message
    assert "install the torchvision" in message and f"tiny-{family}" in message


def _strip(transcripts) -> list[dict]:
    """A transcript without what differs between a live run and a replay of it: timings, cache hits."""
    return [t.to_dict() | {"requests": None, "timing": None} for t in transcripts]


def _scores(run_dir: Path, cache: Path) -> list[dict]:
    from vlmproprio.evaluation import score_run

    prefill_embeddings(run_dir, fake_spec().key, cache)
    tables = score_run(run_dir, encoder=fake_spec(), embedding_cache=cache, n_boot=50, n_perm=50, progress=False)
    return json.loads(json.dumps(tables.rows, sort_keys=True))  # NaN == NaN, as written


@pytest.mark.slow
@pytest.mark.parametrize("family", NEW_FAMILIES)
def test_family_records_and_replays_bit_identically(family: str, tiny_model, door_fixtures: Path, tmp_path: Path):
    from vlmproprio.backends.registry import BackendSettings
    from vlmproprio.backends.tiny import tiny_model_dir

    model = f"tiny-{family}"
    assert tiny_model(family) == tiny_model_dir(family)  # the run below uses the session's build
    conditions = tuple(parse_conditions("both"))
    common = dict(models=(model,), conditions=conditions, fixtures=door_fixtures, episode_ids=(EPISODE,))
    record = RunPlan(
        out=tmp_path / "live",
        mode="record",
        cache_dir=tmp_path / "cache",
        backend=BackendSettings.of(threads=1),
        max_new_tokens=8,
        progress=False,
        **common,
    )
    if _unrunnable(family):
        _refused(family, lambda: run(record))
        return
    [live] = run(record)
    frames = len(load_episode(door_fixtures, EPISODE).frames)
    assert live.stats["misses"] == calls_per_episode(frames, 5)  # every request answered by the model
    [transcript] = live.transcripts
    assert live.cassette is not None
    cassette = read_cassette(live.cassette)
    assert {r.key for r in transcript.requests} <= set(cassette.entries)
    [p3] = [cassette.entries[r.key] for r in transcript.requests if r.stage == "p3"]
    # Process 3 at the image cap: every frame in one request, each at the family's real token cost
    assert p3.meta["prompt_tokens"] > frames * FRAME_TOKENS[family]

    [replayed] = run(RunPlan(out=tmp_path / "replay", mode="replay", progress=False, max_new_tokens=8, **common))
    assert replayed.mode == "replay"
    assert _strip(read_transcripts(tmp_path / "live")) == _strip(read_transcripts(tmp_path / "replay"))
    scores = _scores(tmp_path / "live", tmp_path / "emb")
    assert scores and scores == _scores(tmp_path / "replay", tmp_path / "emb")


def _prompt_tokens(backend, frames: list[Path], n_images: int) -> int:
    from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart, Message, RequestTag, TextPart

    parts = (*(ImagePart(f.read_bytes()) for f in frames[:n_images]), TextPart("Describe the frames."))
    request = ChatRequest(
        (Message("user", parts),), GenerationConfig(max_new_tokens=1), tag=RequestTag("x", "y", "p1", 0)
    )
    return backend.generate([request])[0].meta.prompt_tokens


@pytest.mark.slow
@pytest.mark.parametrize("family", NEW_FAMILIES)
def test_a_frame_costs_the_family_s_tokens(family: str, tiny_model):
    """Frames in one prompt cost what the family's processor gives them (and the image tokens are not counted
    in the text): LLaVA-OneVision's several-image prompts take one view per image, not its single-image tiles."""
    from vlmproprio.backends.hf import HFBackend

    backend = HFBackend(tiny_model(family), model_id=f"tiny-{family}", threads=1)
    if _unrunnable(family):
        _refused(family, backend.load)
        return
    frames = sorted((ROOT / "fixtures" / "episodes" / EPISODE / "frames").glob("*.png"))
    none, one, two = (_prompt_tokens(backend, frames, n) for n in (0, 1, 2))
    each = (two - none) / 2
    # a frame's wrapping tokens (<start_of_image>, row breaks, newlines): a few more than its image tokens
    assert FRAME_TOKENS[family] <= each <= FRAME_TOKENS[family] + 12, (none, one, two)
    if family == "llava-onevision":
        assert one - none > 2 * FRAME_TOKENS[family]  # alone, a frame also gets its anyres tile
    else:
        assert one - none <= FRAME_TOKENS[family] + 12


def _docs_table(heading: str) -> list[list[str]]:
    """The rows of the first table under ``heading`` in docs/models.md, cells stripped of backticks."""
    text = (ROOT / "docs" / "models.md").read_text()
    section = text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")]
    return [[c.strip().strip("`") for c in row.strip("|").split("|")] for row in rows[2:]]  # past header, rule


def test_every_family_has_a_tiny_name_and_the_docs_list_them():
    from vlmproprio.models import REGISTRY, TINY_FAMILY_LABELS, resolve_model

    assert set(FAMILIES) == set(EARLIER) | set(TINY_FAMILY_LABELS)
    for family in FAMILIES:
        assert resolve_model(f"tiny-{family}").tiny_family == family
    assert [row[0] for row in _docs_table("Tiny random builds")] == [f"tiny-{f}" for f in FAMILIES]
    published = {row[0]: row[1] for row in _docs_table("Published checkpoints")}
    registry = {name: ref.weights for name, ref in REGISTRY.items() if ref.kind == "hf" and not ref.tiny_family}
    assert published == registry  # every hf checkpoint of the registry is in the table, with its weights


@pytest.mark.slow
@pytest.mark.parametrize("family", NEW_FAMILIES)
def test_batched_answers_equal_one_by_one(family: str, tiny_model):
    """Left-padded batches of prompts with different image counts (0, 1, 2, 5) answer as the prompts alone do:
    the images of a batch reach the right prompt, in whichever layout the family's processor takes them."""
    from vlmproprio.backends.hf import HFBackend
    from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart, Message, RequestTag, TextPart

    backend = HFBackend(tiny_model(family), model_id=f"tiny-{family}", max_batch_size=4, threads=1)
    if _unrunnable(family):
        _refused(family, backend.load)
        return
    frames = sorted((ROOT / "fixtures" / "episodes" / EPISODE / "frames").glob("*.png"))
    requests = [
        ChatRequest(
            (
                Message(
                    "user", (*(ImagePart(f.read_bytes()) for f in frames[i : i + n]), TextPart("Frame 1:" * (i + 1)))
                ),
            ),
            GenerationConfig(max_new_tokens=6),
            tag=RequestTag(EPISODE, "both", "p1", i),
        )
        for i, n in enumerate((2, 0, 5, 1))
    ]
    assert len(backend.plan_batches(requests)) == 1  # one batch of all four
    batched = backend.generate(requests)
    alone = [backend.generate([r])[0] for r in requests]
    assert [a.text for a in batched] == [a.text for a in alone]
    assert [a.meta.prompt_tokens for a in batched] == [a.meta.prompt_tokens for a in alone]


@pytest.mark.slow
@pytest.mark.parametrize("family", NEW_FAMILIES)
def test_build_is_sha256_identical(family: str, tiny_model, tmp_path: Path):
    from vlmproprio.backends.tiny import build_tiny_model, file_hashes

    first, again = file_hashes(tiny_model(family)), file_hashes(build_tiny_model(family, tmp_path / family))
    assert "model.safetensors" in first and "chat_template.jinja" in first
    assert first == again
