"""The rubric against hand labels: captions written as different VLMs write, labelled by a careful reader.

``tests/data/rubric_agreement.jsonl`` holds one caption per line with the episode it describes (a shipped
fixture episode) and six hand-made labels: object / action / trajectory x mentioned / correct. The labels
say what a person who knows the episode's ground truth decides, not what the scorer says. The test fails
when the rubric agrees on fewer than 95 % of the labels and prints every disagreement, so a regression names
the caption and the label.
"""

from __future__ import annotations

import json
from pathlib import Path

from vlmproprio.episodes import load_episode
from vlmproprio.scoring import ITEMS, score_caption

ROOT = Path(__file__).resolve().parents[2]
AGREEMENT_SET = ROOT / "tests" / "data" / "rubric_agreement.jsonl"
FIXTURES = ROOT / "fixtures"
MIN_AGREEMENT = 0.95
FIELDS = ("mentioned", "correct")


def load_agreement_set() -> list[dict]:
    rows = [json.loads(line) for line in AGREEMENT_SET.read_text(encoding="utf-8").splitlines() if line.strip()]
    return rows


def rubric_disagreements(rows: list[dict]) -> tuple[int, list[str]]:
    """(number of labels compared, one line per label where the rubric and the hand label differ)."""
    episodes = {eid: load_episode(FIXTURES, eid, verify=False) for eid in sorted({r["episode"] for r in rows})}
    n, misses = 0, []
    for r in rows:
        s = score_caption(r["caption"], episodes[r["episode"]])
        for item in ITEMS:
            for what in FIELDS:
                n += 1
                want = r["labels"][item][what]
                got = getattr(s.item(item), what)
                if got != want:
                    misses.append(f"{r['id']}: {item}.{what} rubric={got} hand={want}  | {r['caption']}")
    return n, misses


def test_agreement_set_is_well_formed():
    rows = load_agreement_set()
    assert len(rows) >= 60
    assert len({r["id"] for r in rows}) == len(rows)
    assert len({r["style"] for r in rows}) >= 8
    for r in rows:
        for item in ITEMS:
            lab = r["labels"][item]
            assert set(lab) == set(FIELDS), r["id"]
            assert not (lab["correct"] and not lab["mentioned"]), f"{r['id']}: correct but not mentioned"


def test_rubric_agrees_with_hand_labels():
    n, misses = rubric_disagreements(load_agreement_set())
    agreement = 1 - len(misses) / n
    print(f"\nrubric vs hand labels: {n - len(misses)}/{n} = {agreement:.1%}")
    for m in misses:
        print("  ", m)
    assert agreement >= MIN_AGREEMENT, f"agreement {agreement:.1%} < {MIN_AGREEMENT:.0%}:\n" + "\n".join(misses)


if __name__ == "__main__":  # pragma: no cover - a quick look without pytest
    n, misses = rubric_disagreements(load_agreement_set())
    print(f"{n - len(misses)}/{n} = {1 - len(misses) / n:.1%}")
    print("\n".join(misses))
