"""Reading robosuite / robomimic ``demo.hdf5`` files: what a file says about itself, and one demo's arrays.

File layouts read (both keep one group per demonstration under ``data``)::

    data                      attrs: env (robosuite) or env_args (robomimic: JSON with env_name, env_kwargs),
                                     env_info (robosuite: JSON with robots, controller_configs)
    data/<demo>               attrs: model_file (the MJCF XML the demo ran on)
    data/<demo>/states        (N, 1 + nq + nv) flattened MuJoCo states: time, qpos, qvel; states[t] is the
                              state before actions[t] (robosuite's gather drops the state after the last action)
    data/<demo>/actions       (N, 7) OSC_POSE actions
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlmproprio.errors import VlmproprioError
from vlmproprio.io import special_kind


class DemoImportError(VlmproprioError):
    """A demo file that cannot be imported; the message names the file (and demo) and what is wrong."""


@dataclass(frozen=True)
class DemoFile:
    """What a demo file says about itself."""

    path: Path
    env_name: str
    layout: str  # "robosuite" (env + env_info) | "robomimic" (env_args)
    env_kwargs: dict  # robots, controller_configs, control_freq... as recorded (may be empty)
    demos: tuple[str, ...]
    recorded_with: str | None  # robosuite version that wrote it, when the file says


@dataclass(frozen=True)
class Demo:
    name: str
    model_xml: str
    states: np.ndarray  # (N, 1 + nq + nv)
    actions: np.ndarray | None  # (N, action dim) or None


def _text(value) -> str:
    if isinstance(value, bytes | np.bytes_):
        return value.decode("utf-8")
    return str(value)


def _demo_key(name: str) -> tuple:
    m = re.search(r"(\d+)$", name)
    return (0, int(m.group(1)), name) if m else (1, 0, name)


def _h5py():
    try:
        import h5py
    except ImportError as exc:
        raise DemoImportError("reading demo files needs h5py: pip install 'vlmproprio[record]'") from exc
    return h5py


def _open(path: Path):
    h5py = _h5py()
    path = Path(path)
    kind = special_kind(path)
    if kind is not None:  # h5py would open a FIFO and wait for a writer
        raise DemoImportError(f"{path}: {kind}, not a regular file")
    if not path.is_file():
        raise DemoImportError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise DemoImportError(f"{path}: not a readable HDF5 file ({exc})") from exc


def _json_attr(path: Path, attrs, key: str) -> dict:
    try:
        data = json.loads(_text(attrs[key]))
    except ValueError as exc:
        raise DemoImportError(f"{path}: data.attrs[{key!r}] is not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise DemoImportError(f"{path}: data.attrs[{key!r}] must be a JSON object")
    return data


def read_demo_file(path: Path) -> DemoFile:
    """The environment and demo names of a robosuite or robomimic demo file."""
    h5py = _h5py()
    path = Path(path)
    with _open(path) as f:
        data = f.get("data")
        if not isinstance(data, h5py.Group):
            raise DemoImportError(f"{path}: no 'data' group (not a robosuite or robomimic demo file)")
        attrs = data.attrs
        if "env_args" in attrs:
            args = _json_attr(path, attrs, "env_args")
            env_name, layout = args.get("env_name"), "robomimic"
            kwargs = args.get("env_kwargs") or {}
            recorded_with = args.get("env_version")
        elif "env" in attrs:
            env_name, layout = _text(attrs["env"]), "robosuite"
            kwargs = _json_attr(path, attrs, "env_info") if "env_info" in attrs else {}
            recorded_with = _text(attrs["repository_version"]) if "repository_version" in attrs else None
        else:
            raise DemoImportError(f"{path}: data has neither an 'env' nor an 'env_args' attribute (which env is it?)")
        demos = tuple(
            sorted((k for k in data if isinstance(data[k], h5py.Group) and "states" in data[k]), key=_demo_key)
        )
    if not isinstance(env_name, str) or not env_name:
        raise DemoImportError(f"{path}: no environment name in the file")
    if not demos:
        raise DemoImportError(f"{path}: no demonstrations (no data/<demo>/states)")
    return DemoFile(path, env_name, layout, dict(kwargs), demos, None if recorded_with is None else str(recorded_with))


def read_demo(path: Path, name: str) -> Demo:
    path = Path(path)
    with _open(path) as f:
        grp = f.get(f"data/{name}")
        if grp is None:
            raise DemoImportError(f"{path}: no demo {name!r}")
        where = f"{path} {name}"
        if "model_file" not in grp.attrs:
            raise DemoImportError(f"{where}: no model_file attribute (the MJCF XML the demo ran on)")
        try:
            states = np.asarray(grp["states"][()], dtype=np.float64)
            actions = np.asarray(grp["actions"][()], dtype=np.float64) if "actions" in grp else None
        except (OSError, TypeError, ValueError) as exc:
            raise DemoImportError(f"{where}: cannot read states/actions ({exc})") from exc
        xml = _text(grp.attrs["model_file"])
    if states.ndim != 2 or len(states) < 2:
        raise DemoImportError(
            f"{where}: states must be a (steps, state size) array of 2 or more steps, got {states.shape}"
        )
    if not np.isfinite(states).all():
        raise DemoImportError(f"{where}: non-finite values in states")
    if actions is not None and (actions.ndim != 2 or len(actions) < len(states) - 1):
        actions = None  # unusable for an action replay; the recorded states are still complete
    return Demo(name, xml, states, actions)
