"""What each piece of speed machinery saves, on the shipped fixtures and on a set ten times larger.

    python perf/machinery.py [--model tiny-qwen2-vl] [--repeat 3] [--json OUT]

One process replays and scores the model's cassette (the commands the machinery serves), then times each
piece against the plain standard-library way of doing the same work, on the same data, and checks that the
two give the same bytes:

* ``json``: the score files and the transcripts, ``json_text.dumps_indented`` vs ``json.dumps(indent=1)``;
* ``file digests``: loading and verifying all episodes again in one process, with and without the
  in-process memo of file digests (``episodes.manifest._FILE_DIGESTS``);
* ``pixels``: reading every frame's image with its pixel check, decoded (no ledger) vs vouched for by the
  pixel ledger;
* ``folder digest``: the sentence encoder's revision, hashed vs read from the cross-process memo
  (``digests.folder_digest``);
* ``fork map``: replaying and scoring with one worker vs the default (``parallel.map_groups``): the wall time
  on this machine, and the CPU seconds of this process (with workers: its serial stages and its own chunk,
  about the wall time on free cores) against one worker's, which tell what free cores would give when other
  processes hold the machine's.

The ten-times set repeats the same work ten times (every piece scales with the number of files, frames or
cells, except the encoder's folder, which stays one folder). Each time is the best of ``--repeat`` runs: the
machine is shared, and the minimum is the least disturbed.
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from _common import FIXTURES, emit, machine, table, write_json


def best(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _cpu() -> tuple[float, float]:
    """CPU seconds of this process and of its children that have been waited for."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


def replay_and_score(model: str, out: Path, workers: int) -> tuple[dict, dict, object]:
    """Wall and CPU seconds (``parent_cpu_s``, ``children_cpu_s``) of the replay and of the score."""
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.evaluation import score_run
    from vlmproprio.runner import RunPlan, run

    plan = RunPlan(
        models=(model,),
        conditions=tuple(parse_conditions("all")),
        fixtures=FIXTURES,
        out=out,
        mode="replay",
        progress=False,
        workers=workers,
    )

    def timed(fn) -> tuple[dict, object]:
        (me, kids), t = _cpu(), time.perf_counter()
        value = fn()
        wall = time.perf_counter() - t
        me2, kids2 = _cpu()
        return {"wall_s": wall, "parent_cpu_s": me2 - me, "children_cpu_s": kids2 - kids}, value

    t_run, _ = timed(lambda: run(plan))
    t_score, tables = timed(lambda: score_run(out, fixtures=FIXTURES, workers=workers))
    return t_run, t_score, tables


def fork_map_rows(runs: dict[int, list[tuple[dict, dict]]]) -> dict:
    """Per worker count, the least disturbed replay and score: wall and CPU seconds. On free cores the parent's
    CPU is about the wall time with workers (it runs the serial stages and its own chunk while the children run
    theirs); with one worker the CPU is the whole work."""
    out = {}
    for w, rs in runs.items():
        for i, stage in enumerate(("run", "score")):
            fastest = min((r[i] for r in rs), key=lambda x: x["wall_s"])
            out[f"workers={w}"] = out.get(f"workers={w}", {}) | {
                f"{stage}_s": fastest["wall_s"],
                f"{stage}_parent_cpu_s": min(r[i]["parent_cpu_s"] for r in rs),
                f"{stage}_children_cpu_s": min(r[i]["children_cpu_s"] for r in rs),
            }
    return out


def json_pieces(tables, out: Path, repeat: int) -> dict:
    import vlmproprio.evaluation.formats as formats
    from vlmproprio.evaluation.generations import score_file_texts
    from vlmproprio.json_text import NotPlain, dumps_indented
    from vlmproprio.transcripts import read_transcripts

    docs = [t.to_dict() for t in read_transcripts(out)]

    def fast_transcripts() -> list[str]:
        return [dumps_indented(d) + "\n" for d in docs]

    def plain_transcripts() -> list[str]:
        return [json.dumps(d, indent=1, ensure_ascii=False) + "\n" for d in docs]

    def plain(*_a, **_k):
        raise NotPlain("timing json.dumps")

    fast_scores = score_file_texts(tables, 1)
    t_fast = best(lambda: score_file_texts(tables, 1), repeat)
    saved = formats.dumps_indented
    formats.dumps_indented = plain
    try:
        same = score_file_texts(tables, 1) == fast_scores and fast_transcripts() == plain_transcripts()
        t_plain = best(lambda: score_file_texts(tables, 1), repeat)
    finally:
        formats.dumps_indented = saved
    return {
        "score files fast_s": t_fast,
        "score files plain_s": t_plain,
        "transcripts fast_s": best(fast_transcripts, repeat),
        "transcripts plain_s": best(plain_transcripts, repeat),
        "transcripts": len(docs),
        "same_bytes": same,
    }


def digest_pieces(repeat: int) -> dict:
    from vlmproprio.episodes import load_episodes
    from vlmproprio.episodes import manifest as M

    load_episodes(FIXTURES)  # the page cache warm, the memo filled

    def without_memo():
        M._FILE_DIGESTS.clear()
        load_episodes(FIXTURES)

    t_memo = best(lambda: load_episodes(FIXTURES), repeat)
    t_plain = best(without_memo, repeat)
    load_episodes(FIXTURES)
    return {"load again memo_s": t_memo, "load again plain_s": t_plain}


def pixel_pieces(repeat: int) -> dict:
    from vlmproprio.episodes import frame_images, load_episodes
    from vlmproprio.episodes import pixels as P

    episodes = load_episodes(FIXTURES)
    frames = [f for ep in episodes for f in ep.frames]

    def decoded():
        P._PIXELS_VERIFIED.clear()
        for ep in episodes:
            frame_images(ep.frames)

    def vouched():
        for ep in episodes:
            frame_images(ep.frames)

    t_decode = best(decoded, repeat)
    t_ledger = best(vouched, repeat)
    return {"frames": len(frames), "images decoded_s": t_decode, "images ledger_s": t_ledger}


def folder_pieces(repeat: int) -> dict:
    import vlmproprio.digests as D
    from vlmproprio.embeddings import encoder_spec

    spec = encoder_spec()
    root = Path(spec.path)
    files = sorted(p for p in root.rglob("*") if p.is_file() and ".cache" not in p.parts)
    listing = D.folder_listing(root, files)
    with tempfile.TemporaryDirectory() as memo:
        D.folder_digest(root, files, Path(memo))

        def remembered():
            D._digest.cache_clear()  # a new process: only the memo file
            D.folder_digest(root, files, Path(memo))

        t_memo = best(remembered, repeat)
    t_hash = best(lambda: D.hash_files(root, listing), repeat)
    size = sum(p.stat().st_size for p in files)
    return {"encoder_mb": size / 1e6, "folder memo_s": t_memo, "folder hash_s": t_hash}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="tiny-qwen2-vl")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from vlmproprio.parallel import default_workers

    workers = default_workers()
    res: dict = {"machine": machine(), "model": args.model, "workers": workers}
    with tempfile.TemporaryDirectory() as tmp:
        replay_and_score(args.model, Path(tmp) / "warmup", 1)  # the embedding cache and the page cache filled
        runs = {
            w: [replay_and_score(args.model, Path(tmp) / f"w{w}_{i}", w)[:2] for i in range(args.repeat)]
            for w in sorted({1, workers})
        }
        res["fork map"] = fork_map_rows(runs)
        out = Path(tmp) / "final"
        _, _, tables = replay_and_score(args.model, out, 1)
        res["json"] = json_pieces(tables, out, args.repeat)
    res["file digests"] = digest_pieces(args.repeat)
    res["pixels"] = pixel_pieces(args.repeat)
    res["folder digest"] = folder_pieces(args.repeat)
    emit(res)
    rows = []
    cmd_run = res["fork map"][f"workers={workers}"]["run_s"]
    cmd_score = res["fork map"][f"workers={workers}"]["score_s"]
    pieces = [
        ("json: score files", res["json"]["score files fast_s"], res["json"]["score files plain_s"], cmd_score, 10),
        ("json: transcripts", res["json"]["transcripts fast_s"], res["json"]["transcripts plain_s"], cmd_run, 10),
        (
            "file digests (a 2nd load)",
            res["file digests"]["load again memo_s"],
            res["file digests"]["load again plain_s"],
            cmd_score,
            10,
        ),
        ("pixel ledger", res["pixels"]["images ledger_s"], res["pixels"]["images decoded_s"], cmd_run, 10),
        (
            "folder digest memo",
            res["folder digest"]["folder memo_s"],
            res["folder digest"]["folder hash_s"],
            cmd_score,
            1,
        ),
    ]
    w1 = res["fork map"]["workers=1"]
    if workers > 1:
        wn = res["fork map"][f"workers={workers}"]
        pieces += [
            ("fork map: replay (wall)", cmd_run, w1["run_s"], w1["run_s"], 10),
            ("fork map: score (wall)", cmd_score, w1["score_s"], w1["score_s"], 10),
            # on free cores: one worker's CPU against the parent's CPU with workers (its critical path)
            (
                "fork map: replay (CPU, free cores)",
                wn["run_parent_cpu_s"],
                w1["run_parent_cpu_s"],
                w1["run_parent_cpu_s"],
                10,
            ),
            (
                "fork map: score (CPU, free cores)",
                wn["score_parent_cpu_s"],
                w1["score_parent_cpu_s"],
                w1["score_parent_cpu_s"],
                10,
            ),
        ]
    for name, with_s, without_s, command_s, scale in pieces:
        saved = without_s - with_s
        rows.append(
            {
                "piece": name,
                "with_s": with_s,
                "without_s": without_s,
                "ratio": without_s / with_s if with_s else None,
                "saved_s": saved,
                "command_s": command_s,
                "saved_%": 100 * saved / command_s,
                "saved_10x_s": saved * scale,
            }
        )
    print(table(rows, ["piece", "with_s", "without_s", "ratio", "saved_s", "command_s", "saved_%", "saved_10x_s"]))
    write_json(args.json, res | {"rows": rows})


if __name__ == "__main__":
    main()
