"""The robosuite env a file's demos are replayed in: its class, recorded controller and each demo's own model."""

from __future__ import annotations

from contextlib import AbstractContextManager

from vlmproprio.record import scenes
from vlmproprio.record.demos.files import Demo, DemoFile, DemoImportError
from vlmproprio.record.recorder import HORIZON, prepare_robosuite


def make_import_env(file: DemoFile, task: scenes.TaskInfo, horizon: int):
    """A robosuite env of the demo's class, with its recorded controller and control rate where possible.

    Returns (env, note): note says when the recorded controller could not be used (the default OSC_POSE
    is, and an action replay then cannot be exact; ``auto`` falls back to the recorded states).

    The env gets its offscreen render context at its next reset (``load_demo_model`` reloads it): the sim
    ``suite.make`` builds is replaced before anything is rendered, and a render context costs ~0.7 s of CPU
    with software OpenGL. Frames are unchanged: every sim gets a context of its own either way."""
    kwargs = scenes.env_kwargs(seed=0, horizon=horizon)
    if "control_freq" in file.env_kwargs:
        kwargs["control_freq"] = file.env_kwargs["control_freq"]
    kwargs["has_offscreen_renderer"] = False
    env, note = _make(task.env_name, file.env_kwargs.get("controller_configs"), kwargs)
    # robosuite reads the flag only when a reset sets up a sim (and to check camera observations, which are off)
    env.has_offscreen_renderer = True
    return env, note


def _make(env_name: str, controller: dict | None, kwargs: dict):
    """(env, note): the env with the recorded controller, or with the default one and a note saying why."""
    import robosuite as suite

    if controller:
        try:
            return suite.make(env_name, controller_configs=controller, **kwargs), None
        except Exception as exc:  # any malformed or version-specific controller config: fall back below
            note = f"recorded controller not loadable here ({type(exc).__name__}: {str(exc)[:120]}); default used"
            return suite.make(env_name, **kwargs), note
    return suite.make(env_name, **kwargs), None


def load_demo_model(env, demo: Demo, file: DemoFile, camera: str) -> None:
    """Reset ``env`` onto the demo's model at its first state, as robosuite's DataCollectionWrapper does."""
    where = f"{file.path} {demo.name}"
    try:
        env.reset_from_xml_string(demo.model_xml)
    except Exception as exc:  # parse / compile / reference errors from robosuite and MuJoCo
        raise DemoImportError(
            f"{where}: robosuite could not load the demo's model ({type(exc).__name__}: {str(exc)[:200]}); "
            f"was it recorded with another robosuite version?"
        ) from exc
    m = env.sim.model
    size = 1 + m.nq + m.nv
    if demo.states.shape[1] != size:
        raise DemoImportError(
            f"{where}: states have {demo.states.shape[1]} columns, the model needs {size} (time, qpos, qvel)"
        )
    if camera not in m.camera_names:
        raise DemoImportError(f"{where}: no camera {camera!r} in the model (cameras: {', '.join(m.camera_names)})")
    env.sim.reset()
    env.sim.set_state_from_flattened(demo.states[0])
    env.sim.forward()
    scenes.hide_ghosts(env)


class ImportEnv(AbstractContextManager):
    """One robosuite env for the demos of a file, reloaded from each demo's model XML as robosuite's
    DataCollectionWrapper did between the demos it collected (a reload rebuilds the sim, the controllers and
    the observables' clock, so a demo's replay does not depend on the demos before it).

    A context manager: ``with ImportEnv(...) as env`` closes the env at the end."""

    def __init__(self, file: DemoFile, task: scenes.TaskInfo, camera: str):
        try:
            prepare_robosuite()
        except ImportError as exc:
            raise DemoImportError(
                f"importing demos needs robosuite and mujoco ({exc}): pip install 'vlmproprio[record]'"
            ) from exc
        self.file, self.task, self.camera = file, task, camera
        self.env, self.controller_note = make_import_env(file, task, horizon=HORIZON)
        if camera == scenes.BIN_CAMERA:
            # after robosuite's own processor (edit_model_xml: asset paths), whenever the env loads an XML
            self.env.set_xml_processor(scenes.with_bin_camera)

    def close(self) -> None:
        self.env.close()

    def __exit__(self, *exc) -> None:
        self.close()
