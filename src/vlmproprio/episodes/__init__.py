"""Episodes: the frozen robot recordings every later stage reads.

``types`` (names, ids, value types, the error) → ``pixels`` (frame images and their pixel digest) →
``manifest`` (the sha256 of every fixture file) → ``store`` (the ``Episode`` and ``Frame`` records, load and
verify, write). Everything public is re-exported here: ``from vlmproprio.episodes import load_episodes``.
"""

from __future__ import annotations

from vlmproprio.episodes.manifest import (
    build_manifest,
    check_fixture_file,
    fixture_manifest_of,
    read_manifest,
    update_manifest,
    verify_files,
    write_fixture_file,
    write_manifest,
)
from vlmproprio.episodes.pixels import (
    MAX_LEDGER_BYTES,
    PIXEL_LEDGER_FILE,
    PNG_END,
    PNG_SIGNATURE,
    decode_rgb,
    pixel_ledger,
    pixel_sha256,
    read_checked_png,
    write_png,
)
from vlmproprio.episodes.store import (
    IMAGE_THREADS,
    Episode,
    Frame,
    check_steps,
    episode_metadata,
    frame_images,
    list_episode_ids,
    load_episode,
    load_episodes,
    read_steps,
    write_episode,
    write_steps,
)
from vlmproprio.episodes.types import (
    EE_DIM,
    EPISODE_FILE,
    EPISODE_ID_RE,
    FORMAT_VERSION,
    FRAMES_DIR,
    JOINT_DIM,
    MANIFEST_NAME,
    STATE_CONVENTIONS,
    STEPS_FILE,
    TASKS,
    EpisodeError,
    PhaseSpan,
    StepStates,
    TargetBin,
    check_episode_id,
    standard_episode_ids,
)

# io's writers and file digest, which callers have long imported from here
from vlmproprio.io import atomic_write_bytes, atomic_write_text, sha256_file

__all__ = [
    "EE_DIM",
    "EPISODE_FILE",
    "EPISODE_ID_RE",
    "FORMAT_VERSION",
    "FRAMES_DIR",
    "IMAGE_THREADS",
    "JOINT_DIM",
    "MANIFEST_NAME",
    "MAX_LEDGER_BYTES",
    "PIXEL_LEDGER_FILE",
    "PNG_END",
    "PNG_SIGNATURE",
    "STATE_CONVENTIONS",
    "STEPS_FILE",
    "TASKS",
    "Episode",
    "EpisodeError",
    "Frame",
    "PhaseSpan",
    "StepStates",
    "TargetBin",
    "atomic_write_bytes",
    "atomic_write_text",
    "build_manifest",
    "check_episode_id",
    "check_fixture_file",
    "check_steps",
    "decode_rgb",
    "episode_metadata",
    "fixture_manifest_of",
    "frame_images",
    "list_episode_ids",
    "load_episode",
    "load_episodes",
    "pixel_ledger",
    "pixel_sha256",
    "read_checked_png",
    "read_manifest",
    "read_steps",
    "sha256_file",
    "standard_episode_ids",
    "update_manifest",
    "verify_files",
    "write_episode",
    "write_fixture_file",
    "write_manifest",
    "write_png",
    "write_steps",
]
