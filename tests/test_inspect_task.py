"""The inspect_ai task end to end: the scores in an inspect log equal vlmproprio's own for the same answers.

Three ways in: inspect's mock model (answers recorded per request and replayed through vlmproprio's own
pipeline), the ``vlmproprio/reference`` provider (the same answers as ``vlmproprio run --model reference``),
and the ``inspect eval`` command line through the ``inspect_ai`` entry point declared in pyproject.toml.
"""

from __future__ import annotations

import base64
import hashlib
import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

# checked, not imported: collecting this module on every xdist worker must not cost sentence-transformers'
# ~10 CPU s where no test there embeds a caption (the scorer imports it when one does), nor inspect_ai's ~1.5 s
# (the ``ia`` fixture imports it, and the task module that needs it, when a test here runs)
pytestmark = [
    pytest.mark.skipif(
        importlib.util.find_spec("inspect_ai") is None, reason="the inspect task needs the [inspect] extra"
    ),
    pytest.mark.skipif(
        importlib.util.find_spec("sentence_transformers") is None, reason="segmentation scores need the [embed] extra"
    ),
]

from vlmproprio.chat import ChatRequest, GenerationConfig, ImagePart  # noqa: E402
from vlmproprio.conditions import parse_conditions  # noqa: E402
from vlmproprio.episodes import load_episodes  # noqa: E402
from vlmproprio.errors import UsageError  # noqa: E402
from vlmproprio.evaluation import score_run  # noqa: E402
from vlmproprio.pipeline import PipelineSettings, caption_episodes  # noqa: E402
from vlmproprio.runner import RunPlan, run  # noqa: E402
from vlmproprio.transcripts import Transcript, write_transcript  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "fixtures"
EPISODES = ("door_03", "bin1_00")
CONDITIONS = "none,both,both_shuffled"

# Captions with the rubric's words in them, so that scores are not all zero; which one a frame gets depends on
# its image, so the similarity trace has steps that segmentation can find (or miss).
FRAME_CAPTIONS = (
    "The robot arm moves forward toward the door handle.",
    "The gripper closes on the handle.",
    "The arm turns the handle down.",
    "The arm pulls the door open toward the robot.",
    "The gripper lifts the cereal box up from the bin.",
    "The arm moves the box to the left compartment.",
)
FINALS = (
    "Grasp the door handle, turn it down and pull the door open.",
    "Pick up the cereal box and place it in the far-left compartment of the target bin.",
    "Move the arm.",
)


@pytest.fixture(scope="module")
def ia() -> SimpleNamespace:
    """inspect_ai's API and vlmproprio's task module (which imports inspect_ai)."""
    import inspect_ai
    from inspect_ai.log import read_eval_log
    from inspect_ai.model import ContentImage, ModelOutput, ModelUsage, get_model

    from vlmproprio import inspect as task

    return SimpleNamespace(
        eval=inspect_ai.eval,
        read_eval_log=read_eval_log,
        ContentImage=ContentImage,
        ModelOutput=ModelOutput,
        ModelUsage=ModelUsage,
        get_model=get_model,
        task=task,
        scored=(*task.RUBRIC_METRICS, *task.SEGMENTATION_METRICS),
    )


def _fingerprint_inspect(ia: SimpleNamespace, messages) -> tuple:
    out = []
    for m in messages:
        parts = []
        for c in m.content if not isinstance(m.content, str) else []:
            if isinstance(c, ia.ContentImage):
                data = base64.b64decode(c.image.split(",", 1)[1])
                parts.append(("image", hashlib.sha256(data).hexdigest()))
            else:
                parts.append(("text", c.text))
        out.append((m.role, tuple(parts)))
    return tuple(out)


def _fingerprint_request(request: ChatRequest) -> tuple:
    return tuple(
        (m.role, tuple(("image", p.sha256) if isinstance(p, ImagePart) else ("text", p.text) for p in m.parts))
        for m in request.messages
    )


def _mock_answer(fp: tuple) -> str:
    """A deterministic answer that depends on the request (its process and its images) only."""
    text = "".join(t for _, parts in fp for kind, t in parts if kind == "text")
    images = [h for _, parts in fp for kind, h in parts if kind == "image"]
    if "Summaries of the task:" in text:  # Process 3
        return FINALS[int(hashlib.sha256(text.encode()).hexdigest(), 16) % len(FINALS)]
    if "Described robot arm actions:" in text:  # Process 2
        return FRAME_CAPTIONS[len(images) % len(FRAME_CAPTIONS)]
    n = len(images) or text.count("Frame ") or 5  # Process 1: one caption per frame
    return "\n".join(
        f"Frame {i + 1}: {FRAME_CAPTIONS[int((images[i] if i < len(images) else '0')[:8], 16) % 4 + (2 if 'bin' in text else 0)]}"
        for i in range(n)
    )


def _eval(ia: SimpleNamespace, task, model, log_dir: Path):
    [log] = ia.eval(task, model=model, log_dir=str(log_dir), display="none")
    assert log.status == "success", log.error
    return ia.read_eval_log(log.location)  # what `inspect view` shows: the log as written


def _inspect_rows(ia: SimpleNamespace, log) -> dict[tuple[str, str], dict]:
    out = {}
    for s in log.samples:
        rubric, seg = s.scores["caption_rubric"], s.scores["segmentation"]
        row = rubric.metadata["row"]
        assert {k: rubric.value[k] for k in ia.task.RUBRIC_METRICS} == pytest.approx(
            {k: row[k] for k in ia.task.RUBRIC_METRICS}, nan_ok=True
        )
        out[(s.metadata["episode_id"], s.metadata["condition"])] = {**row, **rubric.value, **seg.value}
    return out


def _suite_rows(run_dir: Path) -> dict[tuple[str, str], dict]:
    tables = score_run(run_dir, fixtures=FIXTURES, comparisons=[], write=False)
    return {(r["episode_id"], r["condition"]): r for r in tables.rows}


def _assert_same_scores(scored: tuple[str, ...], inspect_rows: dict, suite_rows: dict) -> None:
    assert set(inspect_rows) == set(suite_rows) == {(e, c.name) for e in EPISODES for c in parse_conditions(CONDITIONS)}
    for key, mine in inspect_rows.items():
        theirs = suite_rows[key]
        for col, value in theirs.items():
            if col != "model":  # the run folder's model name differs by design
                assert mine[col] == value or (value != value and mine[col] != mine[col]), (key, col)
        for m in scored:  # the values inspect aggregates are the suite's numbers, exactly
            assert mine[m] == theirs[m] or (theirs[m] is None and mine[m] != mine[m]), (key, m)


def test_mock_model_scores_equal_the_suites_for_the_same_answers(ia, tmp_path):
    answered: dict[tuple, str] = {}

    def mock(input, tools, tool_choice, config):
        fp = _fingerprint_inspect(ia, input)
        answered[fp] = _mock_answer(fp)
        assert (config.temperature, config.max_tokens, config.seed) == (0.0, 512, 0)  # the paper's greedy setting
        out = ia.ModelOutput.from_content(model="mockllm", content=answered[fp])
        # usage given, so mockllm does not count tokens with tiktoken (which downloads its vocabulary)
        out.usage = ia.ModelUsage(input_tokens=1, output_tokens=1, total_tokens=2)
        return out

    model = ia.get_model("mockllm/model", custom_outputs=mock)
    task = ia.task.proprio_captions(condition=CONDITIONS, episodes=",".join(EPISODES), fixtures=str(FIXTURES))
    log = _eval(ia, task, model, tmp_path)
    assert log.results.total_samples == len(EPISODES) * 3
    assert any(
        v.metrics["grouped_mean[both]"].value > 0 for v in log.results.scores if v.name in ia.task.RUBRIC_METRICS
    )

    # the same answers through vlmproprio's own pipeline: every request it builds must be one the task sent
    peers = load_episodes(FIXTURES)
    episodes = [e for e in peers if e.episode_id in EPISODES]
    episodes.sort(key=lambda e: EPISODES.index(e.episode_id))

    def replay(requests):
        from vlmproprio.chat import Answer, AnswerMeta

        return [Answer(answered[_fingerprint_request(r)], AnswerMeta("mock", "mock")) for r in requests]

    run_dir = tmp_path / "run"
    transcripts = caption_episodes(
        episodes, parse_conditions(CONDITIONS), replay, "mock", PipelineSettings(), peers=peers, progress=False
    )
    assert len(answered) == sum(len(t.requests) for t in transcripts)  # no request more, none fewer
    for t in transcripts:
        write_transcript(run_dir, t)
    mine = _inspect_rows(ia, log)
    _assert_same_scores(ia.scored, mine, _suite_rows(run_dir))
    # and the transcripts the task kept are the pipeline's
    stored = {(s.metadata["episode_id"], s.metadata["condition"]): s.store[ia.task.TRANSCRIPT_KEY] for s in log.samples}
    for t in transcripts:
        kept = Transcript.from_dict(stored[(t.episode_id, t.condition)])
        assert (kept.frame_texts, [s.text for s in kept.scenes], kept.final) == (
            t.frame_texts,
            [s.text for s in t.scenes],
            t.final,
        )


def test_reference_provider_matches_vlmproprio_run(ia, tmp_path):
    log = _eval(
        ia,
        ia.task.proprio_captions(condition=CONDITIONS, episodes=",".join(EPISODES), fixtures=str(FIXTURES)),
        "vlmproprio/reference",
        tmp_path / "logs",
    )
    run_dir = tmp_path / "run"
    plan = RunPlan(
        models=("reference",),
        conditions=tuple(parse_conditions(CONDITIONS)),
        fixtures=FIXTURES,
        out=run_dir,
        episode_ids=EPISODES,
        mode="live",
        cache_dir=tmp_path / "cache",
        progress=False,
    )
    run(plan)
    _assert_same_scores(ia.scored, _inspect_rows(ia, log), _suite_rows(run_dir))
    words = {k: v["final_words"] for k, v in _inspect_rows(ia, log).items()}
    assert words[("door_03", "both")] > words[("door_03", "none")]  # state in the prompt reached the captioner
    # the headline is the paired difference per condition, not one mean pooled over conditions
    metrics = {v.name: {m.name.split("/")[-1]: m.value for m in v.metrics.values()} for v in log.results.scores}
    paired = sum(words[(e, "both")] - words[(e, "none")] for e in EPISODES) / len(EPISODES)
    assert metrics["final_words"]["both-none"] == pytest.approx(paired)
    for cond in parse_conditions(CONDITIONS):
        mean = sum(words[(e, cond.name)] for e in EPISODES) / len(EPISODES)
        assert metrics["final_words"][f"mean[{cond.name}]"] == pytest.approx(mean)
    assert "mean" not in metrics["final_words"]


def test_messages_round_trip_between_vlmproprio_and_inspect(ia):
    from vlmproprio.conditions import get_condition
    from vlmproprio.pipeline import CellRun

    ep = load_episodes(FIXTURES, ["door_00"])[0]
    cond = get_condition("both")
    from vlmproprio.conditions import frame_states

    cell = CellRun(
        ep, cond, [ImagePart(f.image_bytes()) for f in ep.frames], frame_states(ep, cond), PipelineSettings()
    )
    request = cell.p1_requests()[0]
    back = ia.task.from_inspect_messages(ia.task.to_inspect_messages(request), request.config)
    assert back.messages == request.messages and len(back.images) == 5
    bad = ia.task.to_inspect_messages(request)
    bad[0].content[1] = ia.ContentImage(image="https://example.org/frame.png")
    with pytest.raises(UsageError, match="data URI"):
        ia.task.from_inspect_messages(bad, GenerationConfig())


def test_task_refuses_unknown_episodes_and_conditions(ia):
    with pytest.raises(UsageError, match="unknown episode"):
        ia.task.proprio_captions(episodes="door_99", fixtures=str(FIXTURES))
    with pytest.raises(UsageError, match="unknown condition"):
        ia.task.proprio_captions(condition="bothh", episodes="door_00", fixtures=str(FIXTURES))


@pytest.mark.slow
def test_inspect_eval_command_finds_the_task_through_the_entry_point(ia, tmp_path):
    """`inspect eval vlmproprio/proprio_captions` as a user types it, with the entry point pyproject.toml declares
    (installed here as a tiny dist-info, so the test does not depend on how this checkout was installed).
    door_03 under both is what the reference test above captions: its embeddings are cached by then, which saves
    the subprocess loading the sentence encoder (a speed-up only; the test passes alone too)."""
    tomllib = pytest.importorskip("tomllib", reason="reading pyproject.toml needs Python 3.11")
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["inspect_ai"]
    assert eps == {"vlmproprio": "vlmproprio.inspect"}
    dist = tmp_path / "site" / "vlmproprio_inspect_entry_point-0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: vlmproprio-inspect-entry-point\nVersion: 0\n")
    (dist / "entry_points.txt").write_text("[inspect_ai]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()))
    # vlmproprio itself comes from the environment (the checkout's editable install, or a wheel): with src/ on
    # PYTHONPATH too, inspect finds the setuptools egg-info there and then no task at all
    env = {**os.environ, "PYTHONPATH": str(dist.parent), "COLUMNS": "160"}
    inspect_cli = Path(sys.executable).with_name("inspect")
    cmd = [str(inspect_cli), "eval", "vlmproprio/proprio_captions", "-T", "condition=both", "-T", "episodes=door_03"]
    cmd += ["-T", f"fixtures={FIXTURES}", "--model", "vlmproprio/reference", "--log-dir", str(tmp_path / "logs")]
    proc = subprocess.run(
        [*cmd, "--display", "plain"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    [path] = (tmp_path / "logs").glob("*.eval")
    log = ia.read_eval_log(str(path))
    assert log.status == "success" and log.eval.task == "vlmproprio/proprio_captions"
    assert [s.id for s in log.samples] == ["door_03__both"]
    assert {s.name for s in log.results.scores} == set(ia.scored)
