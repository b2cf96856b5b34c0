"""The tasks demos can be imported as, and which one a demo file is (checked against --task and its robots)."""

from __future__ import annotations

from vlmproprio.record import scenes
from vlmproprio.record.demos.files import DemoFile, DemoImportError

# CLI task names -> what the importer makes of them.
TASKS: dict[str, scenes.TaskInfo] = {
    "door": scenes.DOOR,
    "pick_place_cereal": scenes.PICK_PLACE,
    "pick_place_can": scenes.PICK_PLACE_CAN,
    "lift": scenes.LIFT,
}
SUPPORTED_ENVS = tuple(sorted(t.env_name for t in TASKS.values()))


def task_for(file: DemoFile, task: str | None) -> tuple[str, scenes.TaskInfo]:
    """The importer task for a file: the one asked for, which must match the file's env, or the file's own."""
    by_env = {info.env_name: name for name, info in TASKS.items()}
    if task is not None and task not in TASKS:
        raise DemoImportError(f"unknown task {task!r} (supported: {', '.join(TASKS)})")
    if file.env_name not in by_env:
        raise DemoImportError(
            f"{file.path}: environment {file.env_name!r} is not supported (supported: {', '.join(SUPPORTED_ENVS)})"
        )
    if task is not None and TASKS[task].env_name != file.env_name:
        raise DemoImportError(
            f"{file.path}: the demos are of {file.env_name}, but --task {task} expects {TASKS[task].env_name} "
            f"(use --task {by_env[file.env_name]})"
        )
    robots = _robots(file)
    if robots != ["Panda"]:
        raise DemoImportError(
            f"{file.path}: recorded with robots {robots}; episodes hold the Panda's state (7 joints + gripper)"
        )
    name = by_env[file.env_name]
    return name, TASKS[name]


def _robots(file: DemoFile) -> list[str]:
    robots = file.env_kwargs.get("robots", ["Panda"])
    return [robots] if isinstance(robots, str) else list(robots)
