"""What `vlmproprio --help` and each sub-command's --help say about it."""

from __future__ import annotations

# Commands for the suite's maintainers: not in `vlmproprio --help`'s list (its epilog names them), still runnable.
MAINTAINER_COMMANDS = frozenset({"manifest", "make-tiny-model"})

# Sub-command texts: the line the top-level --help lists, then the description of the command's own --help.
TEXTS: dict[str, tuple[str, str | None]] = {
    "verify": (
        "check fixtures against their manifest and summarise them",
        "Check every file of a fixture folder (episodes, cassettes, caption embeddings) against the sha256 "
        "digests in its manifest.json, and print what it holds: episodes per task, frames, cassettes. Exits "
        "non-zero, naming the file, when one is missing, changed or not listed.",
    ),
    "manifest": (
        "rewrite the fixtures' manifest.json from the files present (maintainers)",
        "Rewrite manifest.json from the files of a fixture folder, after a deliberate change to them (a "
        "re-recording, a new cassette). `verify` then checks against the new digests.",
    ),
    "record": (
        "(re)record the episodes with robosuite (needs the [record] extra)",
        "Re-record episodes with the scripted operators. Bit-identical on this machine kind "
        "(pinned mujoco, EGL or OSMesa rendering). Writes episodes, the manifest and a contact sheet. "
        "With --task T --count N --seed S --out DIR: record a new set of N episodes of varied scenes and "
        "operators instead, in --workers processes, resumable.",
    ),
    "import-demos": (
        "import robosuite / robomimic demo.hdf5 demonstrations as episodes (needs the [record] extra)",
        "Replay each demonstration of a robosuite or robomimic demo.hdf5 in its robosuite env, "
        "render a frame every 20 steps as the recorder does, derive states and ground truth, and write episodes "
        "and the manifest into --out (usable as `vlmproprio run --model reference --fixtures OUT`). Tasks: door, "
        "pick_place_cereal, pick_place_can, lift.",
    ),
    "make-tiny-model": (
        "build a tiny random VLM checkpoint for tests (offline, sha256-reproducible)",
        "Build a tiny random checkpoint (real architecture, ~1 MB, gibberish output) into a folder. "
        "Usable as --model hf:DIR; the registry's tiny-* names build theirs on first use.",
    ),
    "run": (
        "caption episodes with a model under each condition (Processes 1-3)",
        "Run the paper's captioning method: for every episode and condition, Process 1 (a caption "
        "per frame, in groups of k), Process 2 (a scene caption per group) and Process 3 (one final "
        "instruction). Answers are cached by content, so an interrupted run resumes where it stopped.",
    ),
    "models": (
        "the model registry, and per model whether it can run here (cassette, weights) and how to get it",
        "List the registry's models. For each: is its cassette in <fixtures>/responses/ (replay), can "
        "it run live here (weights in a local folder or the local Hugging Face cache, an API key or --base-url), "
        "and if not, how to get what is missing.",
    ),
    "cassette export": (
        "cache -> fixtures/responses/<model>.jsonl (merged with what is there)",
        None,
    ),
    "cassette import": (
        "cassette -> response cache",
        None,
    ),
    "cassette embed": (
        "(re)build <fixtures>/responses/<model>.embeddings.npz: the model's caption embeddings",
        "Replay the model (its cassette; the reference captioner computes its answers) over every "
        "episode and condition of the fixtures, embed every frame caption scoring uses, and store the vectors "
        "beside the cassette (updating the manifest), so that scoring the replay needs no torch. Needs the "
        "encoder (the [embed] extra).",
    ),
    "score": (
        "score a run: caption rubric, segmentation sweep, paired statistics -> RUN_DIR/scores/",
        "Score every transcript of a run against the fixtures' ground truth and write tables "
        "(rows, aggregate, threshold sweep, paired statistics, audit) and a per-frame table (frames.csv) to "
        "RUN_DIR/scores/. Frame-caption embeddings are cached in <cache root>/embeddings (see --cache-dir), so "
        "re-scoring needs no torch.",
    ),
    "report": (
        "tables, plots (paper Figs. 5-8) and an HTML page for a run -> RUN_DIR/report/",
        "Write RUN_DIR/report/: report.md (aggregate and paired tables), PNG plots mirroring the "
        "paper's Figs. 5-8 plus boundary F1 vs threshold, and index.html (summary, plots, tables, every "
        "episode's frames beside its captions with the rubric matches highlighted). Scores the run first "
        "if RUN_DIR/scores/ is missing.",
    ),
    "compare": (
        "metric differences between two runs, or two models in one run",
        "Print the differences B - A of the caption and segmentation metrics per task and "
        "condition, paired by episode, with bootstrap 95% CIs and sign-flip p-values. Rows are matched on "
        "model/task/condition; give --model-a/--model-b to compare two models (inside one run: omit RUN_B).",
    ),
    "leaderboard": (
        "many runs or models side by side: one table, one plot, the verdicts",
        "Print a table of every model in the given scored runs (any number: a tox matrix's runs, a lab's "
        "models) against the headline metrics: the mean under --a and --b and the paired difference with its "
        "bootstrap 95% CI, then each model's verdicts and warnings. With --out, also write index.html, "
        "leaderboard.md, leaderboard.png (the differences with their CIs) and leaderboard.json.",
    ),
    "power": (
        "what the shipped 22 and the extended 216 episodes can detect: power curves, minimal detectable effects",
        "Simulate the suite's paired test (sign-flip, stats.py) over each set's episode structure "
        "(shipped: 10 Door, 12 bins, 22 pooled; extended: 60 Door, 96 pick-place, 60 Stack, 216 pooled) for "
        "effects of known size, at Holm's first-step level alpha / family. "
        "Writes power.json, power.md and power_curves.png to --out.",
    ),
    "export-dataset": (
        "the episodes as a Hugging Face datasets folder (Parquet + card; needs the [dataset] extra)",
        "Write the episodes as a Hugging Face `datasets` dataset: OUT/frames (one row per frame: "
        "image, joints, end-effector pose, ground-truth phase and direction; the default config), OUT/episodes "
        "and OUT/phases as Parquet, and a dataset card OUT/README.md. Load it with "
        "datasets.load_dataset(OUT) or load_dataset(OUT, 'episodes').",
    ),
    "show": (
        "the full prompt of every request of one episode and condition of a run",
        "Re-render every request (Processes 1-3) of one (episode, condition) of a run from the settings "
        "recorded in RUN_DIR/run.json, the fixtures and the answers in the transcript, and print each message's "
        "full text (images as their sha256). Each request's cache key is compared with the one the run recorded; "
        "exit status 1 if any differs (the prompts or fixtures changed since).",
    ),
}
