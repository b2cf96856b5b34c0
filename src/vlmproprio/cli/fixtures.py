"""The fixture folder's commands: verify, manifest, record, import-demos, export-dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from vlmproprio.cli.arguments import add_fixtures, add_list, add_no_progress, command, fixtures_of
from vlmproprio.errors import UsageError
from vlmproprio.options import FIXTURES_HELP, split_list


def cmd_verify(args: argparse.Namespace) -> int:
    from vlmproprio.summary import fixture_summary, format_summary

    root = fixtures_of(args)
    print(format_summary(fixture_summary(root)))
    if args.set is not None:
        from vlmproprio.record.named_sets import require_digests

        print(require_digests(root, args.set).message(root))
    return 0


def cmd_manifest(args: argparse.Namespace) -> int:
    from vlmproprio.episodes import write_manifest

    path = write_manifest(fixtures_of(args))
    print(f"wrote {path}")
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from vlmproprio.record.recorder import record_all

    if args.set is not None:
        return _record_named_set(args)
    if args.write_digests:
        raise UsageError("record --write-digests goes with --set NAME")
    if args.task is not None:
        return _record_new_set(args)
    if args.out is not None or args.count is not None or args.seed is not None:
        raise UsageError("record --out, --count and --seed make a new set: give --task too (or --set NAME)")
    fixtures = fixtures_of(args, must_exist=False)
    sheets = args.contact_sheets or Path("runs") / "contact_sheets"
    record_all(fixtures, episode_ids=split_list(args.episodes) or None, contact_sheets=sheets)
    return 0


def _record_new_set(args: argparse.Namespace) -> int:
    from vlmproprio.parallel import parse_workers
    from vlmproprio.record.sets import record_set

    if args.out is None or args.count is None:
        raise UsageError("record --task needs --count N and --out DIR (and takes --seed S, default 0)")
    if args.episodes:
        raise UsageError("record --episodes re-records shipped episodes; it does not go with --task")
    workers = parse_workers(args.workers, "record --workers") if args.workers is not None else 1
    record_set(
        args.task,
        args.count,
        args.seed or 0,
        args.out,
        workers=workers,
        max_steps=args.max_steps,
        progress=not args.no_progress,
    )
    return 0


def _record_named_set(args: argparse.Namespace) -> int:
    from vlmproprio.parallel import parse_workers
    from vlmproprio.record.named_sets import record_named

    if args.task is not None or args.count is not None or args.seed is not None or args.episodes:
        raise UsageError(
            "record --set NAME records that set's own tasks, counts and seeds: drop --task, --count, "
            "--seed and --episodes"
        )
    if args.out is None:
        raise UsageError(f"record --set {args.set} needs --out DIR")
    workers = parse_workers(args.workers, "record --workers") if args.workers is not None else 1
    record_named(
        args.set,
        args.out,
        workers=workers,
        max_steps=args.max_steps,
        progress=not args.no_progress,
        update_digests=args.write_digests,
    )
    return 0


def cmd_import_demos(args: argparse.Namespace) -> int:
    from vlmproprio.record.demos import import_demos

    results = import_demos(
        args.file,
        args.out,
        args.task,
        camera=args.camera,
        demos=split_list(args.demos) or None,
        replay_mode=args.replay,
        prefix=args.prefix,
        progress=not args.no_progress,
    )
    for r in results:
        print(f"{r['episode_id']}: {r['demo']}, {r['steps']} steps, {r['frames']} frames, {r['replay']} replay")
    wall = sum(r["wall_s"] for r in results)
    print(f"imported {len(results)} demos into {args.out} in {wall:.1f} s ({wall / len(results):.1f} s per demo)")
    return 0


def cmd_export_dataset(args: argparse.Namespace) -> int:
    from vlmproprio.dataset_export import export_dataset

    episodes = split_list(args.episodes) or None
    summary = export_dataset(fixtures_of(args), args.out, episodes, overwrite=args.overwrite)
    print(summary.line())
    return 0


def add_fixture_commands(sub) -> None:
    """verify, manifest, record: the fixture folder itself."""
    p = command(sub, "verify", cmd_verify)
    add_fixtures(p)
    p.add_argument(
        "--set",
        metavar="NAME",
        help="also check the episodes against the committed digests of this "
        "named set (record/named_sets.json: extended)",
    )
    p = command(sub, "manifest", cmd_manifest)
    add_fixtures(p)
    p = command(sub, "record", cmd_record)
    add_fixtures(p, FIXTURES_HELP + "; written if it does not exist")
    add_list(p, "--episodes", "only these episode ids, a comma list or repeated (default: all 22)", "IDS", spaces=True)
    p.add_argument(
        "--contact-sheets",
        type=Path,
        default=None,
        help="folder for one contact sheet per episode (default: runs/contact_sheets)",
    )
    add_new_set_options(p)


def add_new_set_options(p) -> None:
    """record --task T --count N --seed S --out DIR: a new episode set (vlmproprio.record.sets)."""
    g = p.add_argument_group("a new episode set (instead of re-recording the shipped episodes)")
    g.add_argument(
        "--set",
        metavar="NAME",
        help="a named set of record/named_sets.json (extended: 216 episodes), "
        "recorded into --out and checked against its committed digests",
    )
    g.add_argument(
        "--write-digests",
        action="store_true",
        help="with --set: write the set's committed digests "
        "from this recording instead of checking it (maintainers, in a source checkout)",
    )
    g.add_argument("--task", help="task family of record/catalog.json: door | pick_place | stack")
    g.add_argument("--count", type=int, help="episodes in the set")
    g.add_argument("--seed", type=int, help="first robosuite seed of the set (default 0): slot k tries seed S+k first")
    g.add_argument("--out", type=Path, help="folder to record the set into; a killed recording resumes there")
    g.add_argument("--workers", metavar="N", help="processes recording episodes in parallel (default 1)")
    g.add_argument("--max-steps", type=int, help="cut every episode after this many steps, unjudged (tests, timing)")
    add_no_progress(g)


def add_import_demos(sub) -> None:
    p = command(sub, "import-demos", cmd_import_demos)
    p.add_argument("file", type=Path, metavar="FILE.hdf5", help="robosuite or robomimic demo file")
    p.add_argument("--task", help="door | pick_place_cereal | pick_place_can | lift (default: from the file's env)")
    p.add_argument("--out", type=Path, required=True, help="fixture folder to write episodes/ and manifest.json into")
    p.add_argument("--camera", help="camera to render (default: the task's, e.g. vlmproprio_bins for pick-place)")
    add_list(p, "--demos", "only these demos, e.g. demo_1,demo_3 (default: all)", "NAMES")
    p.add_argument(
        "--replay",
        choices=("auto", "actions", "states"),
        default="auto",
        help="actions: re-simulate the recorded actions, checked bit for bit against the recorded states; states: "
        "set the recorded states; auto: actions when they reproduce every state, else states (default)",
    )
    p.add_argument("--prefix", help="episode id prefix (default: imp_<task>, giving ids like imp_door_01)")
    add_no_progress(p)


def add_export_dataset(sub) -> None:
    p = command(sub, "export-dataset", cmd_export_dataset)
    p.add_argument("out", type=Path, metavar="OUT", help="folder to write (must be empty or absent)")
    add_fixtures(p)
    add_list(p, "--episodes", "export these episodes only, a comma list or repeated (default: all)", "IDS")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier export in OUT")
