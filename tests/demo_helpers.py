"""Demo files written the way a person collecting demonstrations writes them, for the importer's tests.

An env made like robosuite's ``collect_human_demonstrations.py`` makes it, wrapped by robosuite's own
``DataCollectionWrapper`` (which saves the model XML and the flattened state of every step), driven by
a policy; ``write_demo_hdf5`` then turns the wrapper's folders into ``demo.hdf5`` like robosuite's
``gather_demonstrations_as_hdf5`` (or robomimic's ``env_args`` variant of the same layout).

Differences from robosuite's script, on purpose: every demo is kept (the script keeps successful ones
only, and a test's demo is cut short), and the actions come from the caller rather than from the
wrapper's pickled ``action_infos`` (the very actions it was stepped with), so nothing is unpickled.
"""

from __future__ import annotations

import datetime
import gc
import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlmproprio.record import scenes
from vlmproprio.record.recorder import HORIZON, prepare_robosuite


@dataclass
class RawDemo:
    directory: Path  # the wrapper's ep_* folder
    actions: np.ndarray


@contextmanager
def frozen_gc() -> Iterator[None]:
    """robosuite runs a full ``gc.collect()`` whenever it frees a sim (every env close and every reload from a
    model XML), which walks every object pytest and the project have loaded: ~60 ms a time. Inside the block the
    objects that were alive before it are left out of those walks (``gc.freeze``), which still free everything
    the block made; afterwards the frozen objects are collectable again. No output depends on it."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def collecting_env(env_name: str, seed: int, directory: Path, camera: str | None = None):
    """A reset robosuite env under DataCollectionWrapper. With ``camera`` = the bin camera, the live env gets it
    through an XML processor while the saved model XML stays robosuite's own (as in a user's demo file)."""
    prepare_robosuite()
    import robosuite as suite
    from robosuite.wrappers import DataCollectionWrapper

    class Collecting(DataCollectionWrapper):
        """Renders only on the sims the wrapper reloads from the model XML (what the demos run on): the sim
        ``suite.make`` builds is never rendered, and a render context costs ~0.7 s of CPU (software OpenGL).
        Frames are unchanged: every sim gets a context of its own either way."""

        def _start_new_episode(self):
            self.env.has_offscreen_renderer = True  # robosuite reads it when a reset sets up a sim
            super()._start_new_episode()

    env = suite.make(env_name, **(scenes.env_kwargs(seed, HORIZON) | {"has_offscreen_renderer": False}))
    if camera == scenes.BIN_CAMERA:
        env.set_xml_processor(scenes.with_bin_camera)
    wrapped = Collecting(env, str(directory))
    wrapped.reset()
    scenes.hide_ghosts(env)
    return wrapped


def end_demo(wrapped, actions: Sequence[np.ndarray]) -> RawDemo:
    """One more step, so that the state after the last real action survives gather's dropping of the last
    state. The wrapper writes the demo's files at the next ``next_demo`` or at ``close()``."""
    extra = np.zeros(7)
    extra[6] = -1.0
    wrapped.step(extra)
    return RawDemo(Path(wrapped.ep_directory), np.array([*actions, extra]))


def next_demo(wrapped) -> None:
    """Start the next demo in the same env, as the collection script does between demos."""
    wrapped.reset()
    scenes.hide_ghosts(wrapped.env)


def write_demo_hdf5(
    path: Path, env_name: str, demos: Sequence[RawDemo], *, layout: str = "robosuite", first: int = 1
) -> Path:
    """robosuite's gather_demonstrations_as_hdf5 (or robomimic's env_args layout) over raw demos."""
    import h5py
    import robosuite
    from robosuite.controllers import load_composite_controller_config

    info = {
        "env_name": env_name,
        "robots": ["Panda"],
        "controller_configs": load_composite_controller_config(controller=None, robot="Panda"),
    }
    with h5py.File(path, "w") as f:
        grp = f.create_group("data")
        for i, raw in enumerate(demos):
            states = []
            for state_file in sorted(raw.directory.glob("state_*.npz")):
                with np.load(state_file, allow_pickle=False) as dic:
                    states.extend(dic["states"])
                    assert str(dic["env"]) == env_name, (str(dic["env"]), env_name)
            del states[-1]  # recorded after the last action (gather does the same)
            assert len(states) == len(raw.actions), (len(states), len(raw.actions))
            ep = grp.create_group(f"demo_{first + i}")
            ep.attrs["model_file"] = (raw.directory / "model.xml").read_text()
            ep.create_dataset("states", data=np.array(states))
            ep.create_dataset("actions", data=raw.actions)
            if layout == "robomimic":
                ep.attrs["num_samples"] = len(states)
        now = datetime.datetime.now()
        if layout == "robomimic":
            kwargs = {k: v for k, v in info.items() if k != "env_name"} | {"control_freq": scenes.CONTROL_FREQ}
            grp.attrs["env_args"] = json.dumps(
                {"env_name": env_name, "type": 1, "env_version": robosuite.__version__, "env_kwargs": kwargs}
            )
            grp.attrs["total"] = sum(len(d.actions) for d in demos)
        else:
            grp.attrs["date"] = f"{now.month}-{now.day}-{now.year}"
            grp.attrs["time"] = f"{now.hour}:{now.minute}:{now.second}"
            grp.attrs["repository_version"] = robosuite.__version__
            grp.attrs["env"] = env_name
            grp.attrs["env_info"] = json.dumps(info)
    return path
