"""The README and docs/ hold together: every relative link (and its #anchor) resolves, and the facts a test can
check are current (the inspect task's sample output names the metrics the task reports)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from vlmproprio.evaluation.metrics import caption_metrics, segmentation_paired

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "perf" / "README.md"]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _prose(text: str) -> str:
    """The text outside fenced code blocks (a link-like string in a code sample is not a link)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def heading_anchors(text: str) -> set[str]:
    """GitHub's anchors for a Markdown file's headings: lower case, punctuation dropped, spaces as hyphens."""
    anchors = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*$", _prose(text), flags=re.M):
        anchors.add(re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-"))
    return anchors


def broken_links(doc: Path) -> list[str]:
    """The relative links of ``doc`` whose file does not exist, or whose #anchor is no heading there."""
    broken = []
    for target in LINK.findall(_prose(doc.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        if not dest.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in heading_anchors(dest.read_text(encoding="utf-8")):
            broken.append(f"{target} (no heading #{anchor} in {dest.name})")
    return broken


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_resolves(doc: Path) -> None:
    assert broken_links(doc) == [], f"{doc.relative_to(REPO)} links to what is not there"


def test_a_broken_link_and_a_wrong_anchor_are_found(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Other\n\n## The gates in your own CI, without torch\n")
    doc = tmp_path / "doc.md"
    doc.write_text(
        "[ok](other.md#the-gates-in-your-own-ci-without-torch) [gone](missing.md) [bad](other.md#nowhere)\n"
        "```bash\necho [not a link](nowhere.md)\n```\n"
    )
    assert broken_links(doc) == ["missing.md (no such file)", "other.md#nowhere (no heading #nowhere in other.md)"]


def test_the_inspect_sample_output_shows_every_metric_the_task_reports() -> None:
    text = (REPO / "docs" / "integrations.md").read_text(encoding="utf-8")
    sample = text.split("Real output of the first command", 1)[1].split("```", 2)[1]
    shown = {w for w in re.findall(r"\b(?:final|seg)_\w+", sample)}
    reported = set(caption_metrics()) | {m.replace("seg_loo_", "seg_") for m in segmentation_paired()}
    assert len(reported) == 14 and shown == reported
    assert f"all {len(reported)} values equal" in text
