"""Old parser (a parsing.py given on the command line) against the current one, over every answer the
shipped models give: the reference and reference-state captioners (run live over the fixtures) and the
tiny-qwen2-vl cassette. Prints counts of captions and statuses that differ, and the first few differences.

    .venv/bin/python scripts/compare_parsers.py OLD_PARSING_PY
"""

from __future__ import annotations

import importlib.util
import json
import sys
from collections import Counter
from pathlib import Path

from vlmproprio import parsing, pipeline
from vlmproprio.backends.reference import ReferenceBackend
from vlmproprio.backends.reference_state import ReferenceStateBackend
from vlmproprio.conditions import parse_conditions
from vlmproprio.episodes import load_episodes

FIXTURES = Path("fixtures")


def load_old(path: str):
    spec = importlib.util.spec_from_file_location("old_parsing", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["old_parsing"] = module
    spec.loader.exec_module(module)
    return module


def compare(old, name: str, calls: list[tuple[str, str, int, int]], out: Counter, shown: list) -> None:
    for stage, text, count, offset in calls:
        if stage == "p1":
            a = [(p.text, p.status) for p in old.parse_frame_captions(text, count)]
            b = [(p.text, p.status) for p in parsing.parse_frame_captions(text, count, offset=offset)]
        else:
            a = [(old.parse_single(text).text, old.parse_single(text).status)]
            b = [(parsing.parse_single(text).text, parsing.parse_single(text).status)]
        out[f"{name} {stage} answers"] += 1
        out[f"{name} {stage} captions"] += len(a)
        for x, y in zip(a, b, strict=True):
            out[f"{name} {stage} old {x[1]}"] += 1
            if x != y:
                out[f"{name} {stage} differ"] += 1
                if len(shown) < 12:
                    shown.append((name, stage, text[:160], x, y))


def live_calls(backend) -> list[tuple[str, str, int, int]]:
    calls: list[tuple[str, str, int, int]] = []
    episodes = load_episodes(FIXTURES)
    answers: dict = {}

    def answer(requests):
        got = backend.generate(requests)
        for r, a in zip(requests, got, strict=True):
            answers[id(r)] = a.text
        return got

    real = pipeline.CellRun.accept_p1

    def accept_p1(self, ans):
        for members, a in zip(self.groups, ans, strict=True):
            calls.append(("p1", a.text, len(members), members.start))
        return real(self, ans)

    def accept_p2(self, ans):
        calls.extend(("p2", a.text, 0, 0) for a in ans)
        return real_p2(self, ans)

    def accept_p3(self, a):
        calls.append(("p3", a.text, 0, 0))
        return real_p3(self, a)

    real_p2, real_p3 = pipeline.CellRun.accept_p2, pipeline.CellRun.accept_p3
    pipeline.CellRun.accept_p1, pipeline.CellRun.accept_p2, pipeline.CellRun.accept_p3 = accept_p1, accept_p2, accept_p3
    try:
        pipeline.caption_episodes(episodes, parse_conditions("all"), answer, "x", progress=False)
    finally:
        pipeline.CellRun.accept_p1, pipeline.CellRun.accept_p2, pipeline.CellRun.accept_p3 = real, real_p2, real_p3
    return calls


def cassette_calls(path: Path) -> list[tuple[str, str, int, int]]:
    lengths = {e.episode_id: len(e.frames) for e in load_episodes(FIXTURES)}
    calls = []
    for line in path.read_text(encoding="utf-8").splitlines()[1:]:
        row = json.loads(line)
        tag, text = row["tag"], row.get("text", "")
        if tag["stage"] == "p1":
            groups = pipeline.groups(lengths[tag["episode_id"]], 5)
            members = groups[tag["group"]]
            calls.append(("p1", text, len(members), members.start))
        else:
            calls.append((tag["stage"], text, 0, 0))
    return calls


def main(old_path: str) -> None:
    old = load_old(old_path)
    out: Counter = Counter()
    shown: list = []
    compare(old, "reference", live_calls(ReferenceBackend()), out, shown)
    compare(old, "reference-state", live_calls(ReferenceStateBackend()), out, shown)
    compare(old, "tiny-qwen2-vl", cassette_calls(Path("fixtures/responses/tiny-qwen2-vl.jsonl")), out, shown)
    for k in sorted(out):
        print(f"{k}: {out[k]}")
    for s in shown:
        print(repr(s))


if __name__ == "__main__":
    main(sys.argv[1])
