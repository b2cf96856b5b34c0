"""openai backend concurrency: N requests at concurrency c against a server that takes 200 ms per answer.

    python perf/openai_concurrency.py [--requests 64] [--latency 0.2] [--concurrency 1 2 4 8 16]

The server is the suite's loopback FakeOpenAIServer (a real HTTP server on
127.0.0.1 that the openai SDK talks to as to vLLM) with an artificial latency
per request. The requests are real Process 1 requests made by the pipeline
(up to 5 PNG frames each, sent base64-encoded), answered through the suite's
own path: ``Answerer`` (live, no cache) -> ``OpenAIBackend``. With the
latency dominating, N requests at concurrency c should take about N * latency / c
(at least ceil(N / c) whole rounds of one latency each).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from _common import FIXTURES, emit, machine, table, write_json


def p1_requests(n: int) -> list:
    """The first ``n`` Process 1 requests of the pipeline's wave (all 22 episodes x 8 conditions)."""
    from vlmproprio.backends.reference import ReferenceBackend
    from vlmproprio.conditions import parse_conditions
    from vlmproprio.episodes import load_episodes
    from vlmproprio.pipeline import caption_episodes

    wave: list = []
    reference = ReferenceBackend()

    def answer(requests):
        wave.extend(r for r in requests if r.tag.stage == "p1")
        return reference.generate(requests)

    episodes = load_episodes(FIXTURES)
    caption_episodes(episodes, parse_conditions("all"), answer, "reference", chunk=10**9, progress=False)
    if len(wave) < n:
        raise SystemExit(f"only {len(wave)} Process 1 requests in the fixtures; ask for fewer")
    return wave[:n]


def without_images(request):
    import dataclasses

    from vlmproprio.chat import ImagePart

    messages = tuple(
        dataclasses.replace(m, parts=tuple(p for p in m.parts if not isinstance(p, ImagePart)))
        for m in request.messages
    )
    return dataclasses.replace(request, messages=messages)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--requests", type=int, default=64)
    ap.add_argument("--latency", type=float, default=0.2, help="server seconds per request")
    ap.add_argument("--concurrency", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    ap.add_argument("--text-only", action="store_true", help="leave the images out (the transport's own overhead)")
    ap.add_argument("--out", type=Path, help="also write the numbers as JSON here")
    args = ap.parse_args(argv)

    from vlmproprio.answering import Answerer
    from vlmproprio.backends.openai import OpenAIBackend
    from vlmproprio.testing.openai_server import FakeOpenAIServer

    requests = p1_requests(args.requests)
    if args.text_only:
        requests = [without_images(r) for r in requests]
    body_mb = sum(len(img.data) for r in requests for img in r.images) * 4 / 3 / 2**20
    info = {"what": "machine", **machine(), "requests": len(requests), "base64_images_mb": round(body_mb, 1)}
    emit(info)
    rows = []
    with FakeOpenAIServer(latency_s=args.latency) as server:
        for c in args.concurrency:
            backend = OpenAIBackend("bench-model", base_url=server.base_url, concurrency=c)
            server.max_in_flight = 0
            try:
                backend.generate(requests[:1])  # connection pool and SDK set up before the clock starts
                cached = Answerer(backend, mode="live", cache=None)
                before = len(server.chat_requests)
                t0 = time.perf_counter()
                answers = cached.answer(requests)
                wall = time.perf_counter() - t0
                sent = len(server.chat_requests) - before  # equal requests are asked once
            finally:
                backend.close()
            assert len(answers) == len(requests) and all(a.text.startswith("echo ") for a in answers)
            ideal = sent * args.latency / c
            rounds = -(-sent // c) * args.latency  # whole rounds of c requests: the least it can take
            row = {
                "concurrency": c,
                "requests": sent,
                "wall_s": wall,
                "ideal_s": ideal,
                "wall_over_ideal": wall / ideal,
                "whole_rounds_s": rounds,
                "req_per_s": sent / wall,
                "max_in_flight": server.max_in_flight,
            }
            rows.append(row)
            emit({"what": "concurrency", **row})
    print()
    what = "text only" if args.text_only else f"{body_mb:.1f} MB of base64 images"
    print(f"{len(requests)} Process 1 requests ({what}; equal ones are sent once), server latency {args.latency} s")
    cols = ["concurrency", "requests", "wall_s", "ideal_s", "wall_over_ideal", "whole_rounds_s", "req_per_s"]
    print(table(rows, [*cols, "max_in_flight"]))
    write_json(args.out, {"machine": info, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
