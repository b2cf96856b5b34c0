"""Named episode sets (``vlmproprio record --set extended --out DIR``) and their committed digests.

A named set is a list of parts, each a set (task, count, seed) of ``record/catalog.json``, recorded into one
folder (``record/named_sets.json``). Its episodes are too large to commit (the extended set: ~2.4 MB an episode,
~520 MB in all), so what is committed is one digest per episode (``record/set_digests/<name>.json``): the
sha256 of the episode's files and their sha256s, in path order. Recording a named set ends by checking every
episode against them, so anyone who regenerates the set knows it is the same, bit for bit, as the one the
numbers in the docs were measured on.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

from vlmproprio.errors import UsageError, VlmproprioError
from vlmproprio.io import atomic_write_text, load_json
from vlmproprio.record.catalog import CatalogError, SlotPlan, set_plan

SETS_FILE = "named_sets.json"
DIGESTS_DIR = "set_digests"
DIGESTS_VERSION = 1


class SetDigestError(VlmproprioError):
    """A recorded named set differs from its committed digests."""


@dataclass(frozen=True)
class Part:
    task: str
    count: int
    seed: int


@dataclass(frozen=True)
class NamedSet:
    name: str
    about: str
    parts: tuple[Part, ...]

    @property
    def count(self) -> int:
        return sum(p.count for p in self.parts)

    def plans(self) -> list[SlotPlan]:
        return [plan for p in self.parts for plan in set_plan(p.task, p.count, p.seed)]

    def doc(self) -> dict:
        """What ``DIR/recording.json`` says of the set (the versions are added by the recorder)."""
        return {"set": self.name, "parts": [{"task": p.task, "count": p.count, "seed": p.seed} for p in self.parts]}


@cache
def named_sets() -> dict[str, NamedSet]:
    raw = resources.files("vlmproprio").joinpath("record", SETS_FILE).read_text()
    try:
        data = json.loads(raw)
        return {
            name: NamedSet(
                name,
                spec.get("about", ""),
                tuple(Part(p["task"], int(p["count"]), int(p["seed"])) for p in spec["parts"]),
            )
            for name, spec in data["sets"].items()
        }
    except (KeyError, TypeError, ValueError) as exc:
        raise CatalogError(f"vlmproprio/record/{SETS_FILE}: malformed ({exc!r})") from exc


def named_set(name: str) -> NamedSet:
    known = named_sets()
    if name not in known:
        raise UsageError(f"unknown episode set {name!r} for --set (known: {', '.join(known)})")
    return known[name]


def episode_digests(root: Path) -> dict[str, str]:
    """One digest per episode of the fixture folder ``root``, from its manifest once every file is checked
    against it (the file hashes a verify in this process made are not made again): sha256 over the lines
    ``<path inside the episode> <sha256>``, in path order."""
    from vlmproprio.episodes import read_manifest, verify_files

    verify_files(root)
    lines: dict[str, list[str]] = {}
    for rel, sha in read_manifest(root).items():
        parts = rel.split("/", 2)
        if len(parts) == 3 and parts[0] == "episodes":
            lines.setdefault(parts[1], []).append(f"{parts[2]} {sha}\n")
    return {ep: hashlib.sha256("".join(sorted(ls)).encode()).hexdigest() for ep, ls in sorted(lines.items())}


def digests_path(name: str) -> Path:
    """The committed digests of a named set (inside the package: written by ``record --set NAME
    --write-digests``, which only a source checkout can do)."""
    return Path(str(resources.files("vlmproprio").joinpath("record", DIGESTS_DIR, f"{name}.json")))


def write_digests(root: Path, name: str, versions: dict) -> Path:
    path = digests_path(name)
    doc = {"version": DIGESTS_VERSION, "set": name, "versions": versions, "episodes": episode_digests(root)}
    atomic_write_text(path, json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return path


def committed_digests(name: str) -> dict:
    path = digests_path(name)
    if not path.is_file():
        raise SetDigestError(f"{path}: no committed digests for the episode set {name!r}")
    doc = load_json(path, error=SetDigestError)
    if not isinstance(doc, dict) or not isinstance(doc.get("episodes"), dict):
        raise SetDigestError(f"{path}: malformed (no 'episodes' table)")
    return doc


@dataclass(frozen=True)
class DigestCheck:
    name: str
    matching: int
    differing: tuple[str, ...]
    missing: tuple[str, ...]
    extra: tuple[str, ...]
    committed_versions: dict
    versions: dict

    @property
    def ok(self) -> bool:
        return not (self.differing or self.missing or self.extra)

    def message(self, root: Path) -> str:
        if self.ok:
            return f"{root}: all {self.matching} episodes match the committed digests of the set {self.name!r}"
        lines = [
            f"{root}: the episode set {self.name!r} differs from its committed digests ({digests_path(self.name)})"
        ]
        for label, ids in (("differing", self.differing), ("missing", self.missing), ("not in the set", self.extra)):
            if ids:
                shown = ", ".join(ids[:8]) + (f" and {len(ids) - 8} more" if len(ids) > 8 else "")
                lines.append(f"  {len(ids)} {label}: {shown}")
        if self.committed_versions and self.versions and self.committed_versions != self.versions:
            lines.append(
                f"  recorded with {json.dumps(self.versions, sort_keys=True)}; the digests were made with "
                f"{json.dumps(self.committed_versions, sort_keys=True)}: rendering differs between versions"
            )
        return "\n".join(lines)


def require_digests(root: Path, name: str) -> DigestCheck:
    """``check_digests``, a SetDigestError naming what differs when the check fails."""
    check = check_digests(root, name)
    if not check.ok:
        raise SetDigestError(check.message(root))
    return check


def check_digests(root: Path, name: str) -> DigestCheck:
    """Compare the episodes under ``root`` with the committed digests of the named set."""
    committed = committed_digests(name)
    want: dict[str, str] = committed["episodes"]
    have = episode_digests(root)
    rec = load_json(root / "recording.json", error=SetDigestError) if (root / "recording.json").is_file() else {}
    return DigestCheck(
        name=name,
        matching=sum(have.get(ep) == d for ep, d in want.items()),
        differing=tuple(ep for ep, d in want.items() if ep in have and have[ep] != d),
        missing=tuple(ep for ep in want if ep not in have),
        extra=tuple(ep for ep in have if ep not in want),
        committed_versions=committed.get("versions") or {},
        versions=(rec.get("versions") if isinstance(rec, dict) else None) or {},
    )


def record_named(
    name: str,
    out: Path,
    *,
    workers: int = 1,
    max_steps: int | None = None,
    progress: bool = True,
    update_digests: bool = False,
) -> DigestCheck | None:
    """Record the episodes of the named set missing from ``out``, then check them all against the committed
    digests (SetDigestError when one differs), or, with ``update_digests``, write those digests. A set cut short
    (``max_steps``) is not checked: its digests are not the set's. Returns the check, None when there was none."""
    from vlmproprio.record.recorder import versions
    from vlmproprio.record.sets import record_plans, with_versions

    ns = named_set(name)
    out = Path(out)
    doc = with_versions(ns.doc(), max_steps)
    record_plans(ns.plans(), out, doc, workers=workers, max_steps=max_steps, progress=progress, desc=f"set {name}")
    if max_steps is not None:
        if update_digests:
            raise UsageError("record --write-digests: a set cut short by --max-steps is not the set; record it whole")
        print(f"{out}: cut short by --max-steps, so not checked against the committed digests of {name!r}")
        return None
    if update_digests:
        print(f"wrote {write_digests(out, name, versions())}")
        return None
    check = require_digests(out, name)
    print(check.message(out))
    return check
