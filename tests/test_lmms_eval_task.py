"""The lmms-eval task in docs/lmms_eval/ without lmms-eval (it cannot be installed here: it pulls another torch,
torchvision and numpy 2). The YAML is read as lmms-eval reads it (``!function utils.x``), the dataset is loaded
with the call lmms-eval makes, and each function is checked against vlmproprio itself: the prompt equals the
pipeline's Process 1 request for a one-frame group, and the aggregated segmentation equals ``score_run``'s."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

yaml = pytest.importorskip("yaml")
# checked, not imported (see tests/test_inspect_task.py): the scorer imports sentence-transformers when a caption
# is embedded, the test below imports datasets; collecting the module on every xdist worker costs neither
pytestmark = [
    pytest.mark.skipif(importlib.util.find_spec("datasets") is None, reason="the export needs the [dataset] extra"),
    pytest.mark.skipif(
        importlib.util.find_spec("sentence_transformers") is None, reason="segmentation scores need the [embed] extra"
    ),
]

from vlmproprio.chat import Answer, AnswerMeta, ImagePart, TextPart  # noqa: E402
from vlmproprio.conditions import frame_states, get_condition  # noqa: E402
from vlmproprio.dataset_export import export_dataset  # noqa: E402
from vlmproprio.episodes import load_episodes  # noqa: E402
from vlmproprio.evaluation import score_run  # noqa: E402
from vlmproprio.pipeline import CellRun, PipelineSettings  # noqa: E402
from vlmproprio.transcripts import FrameCaption, Transcript, write_transcript  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TASK_DIR = ROOT / "docs" / "lmms_eval"
FIXTURES = ROOT / "fixtures"
EPISODES = ["door_00", "bin2_01"]
CAPTIONS = ("The arm moves toward the handle.", "The gripper closes.", "The arm pulls the door open.")


def _load_task() -> dict:
    spec = importlib.util.spec_from_file_location("vlmproprio_lmms_utils", TASK_DIR / "utils.py")
    utils = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(utils)

    class Loader(yaml.SafeLoader):
        pass

    def function(loader, node):
        module, name = loader.construct_scalar(node).split(".")
        assert module == "utils"
        return getattr(utils, name)

    Loader.add_constructor("!function", function)
    return yaml.load((TASK_DIR / "vlmproprio_frames.yaml").read_text(), Loader=Loader)


def test_lmms_eval_task_uses_vlmproprios_prompt_parser_and_segmentation(tmp_path):
    import datasets

    task = _load_task()
    out = tmp_path / task["dataset_path"]
    export_dataset(FIXTURES, out, EPISODES)
    docs = datasets.load_dataset(
        path=str(out),
        name=task["dataset_name"],
        download_mode=datasets.DownloadMode.REUSE_DATASET_IF_EXISTS,
        cache_dir=str(tmp_path / "hf"),
    )[task["test_split"]]
    kwargs = task["lmms_eval_specific_kwargs"]["default"]
    cond = get_condition(kwargs["condition"])
    episodes = {e.episode_id: e for e in load_episodes(FIXTURES, EPISODES)}
    cells = {
        eid: CellRun(
            ep, cond, [ImagePart(f.image_bytes()) for f in ep.frames], frame_states(ep, cond), PipelineSettings(k=1)
        )
        for eid, ep in episodes.items()
    }
    requests = {eid: cell.p1_requests() for eid, cell in cells.items()}

    items: dict[str, list] = {}
    answers: dict[str, list[str]] = {eid: [] for eid in EPISODES}
    for doc in docs:
        [image] = task["doc_to_visual"](doc)
        assert image.size == (256, 256)
        request = requests[doc["episode_id"]][doc["frame_index"]]  # the pipeline's request for this frame, k = 1
        expected = "".join(p.text for m in request.messages for p in m.parts if isinstance(p, TextPart))
        assert task["doc_to_text"](doc, kwargs) == expected
        i = doc["frame_index"]
        answer = f"Frame 1: {CAPTIONS[(i // 4) % len(CAPTIONS)]}" if i % 7 else ("" if i % 2 else "I cannot tell.")
        result = task["process_results"](doc, [answer])
        for metric, item in result.items():
            items.setdefault(metric, []).append(item)
        answers[doc["episode_id"]].append(answer)
    got = {m["metric"]: m["aggregation"](items[m["metric"]]) for m in task["metric_list"]}

    # the same answers parsed by the pipeline (Process 1, groups of one frame) and scored by the suite
    run_dir = tmp_path / "run"
    for eid, raws in answers.items():
        ep, cell = episodes[eid], cells[eid]
        cell.accept_p1([Answer(raw, AnswerMeta("lmms", "lmms")) for raw in raws])
        frames = [FrameCaption(i, ep.frames[i].step, p.text, p.status) for i, p in enumerate(cell.frame_captions)]
        write_transcript(run_dir, Transcript("lmms", eid, ep.task, cond.name, "", frames, [], "", "missing"))
    rows = score_run(run_dir, fixtures=FIXTURES, comparisons=[], write=False).rows
    for metric, column in (("vlmproprio_seg_f1_tol1", "seg_f1_tol1"), ("vlmproprio_seg_edit", "seg_edit")):
        values = [r[column] for r in rows if r[column] is not None]
        assert got[metric] == math.fsum(values) / len(values)
    assert not np.isnan(got["vlmproprio_seg_f1_tol1"])


def test_lmms_eval_task_refuses_conditions_one_frame_cannot_give():
    task = _load_task()
    with pytest.raises(ValueError, match="one frame's own state"):
        task["doc_to_text"]({"joints": [0.0] * 8, "ee": [0.0] * 6}, {"condition": "primitives"})
