"""Import human demonstrations from robosuite / robomimic ``demo.hdf5`` files as episodes.

Both file layouts (robosuite's and robomimic's) keep one group per demonstration under ``data`` (``files``).

Each demo is loaded into the matching robosuite env from its own model XML (our
bin camera added for pick-and-place, see ``scenes.with_bin_camera``; the ghost
objects hidden), replayed, and observed with the recorder's own ``Tracer``: a
state row per step, a frame every 20 steps and one on the demo's last state
(the recorder rests until a sampled step instead; an imported demo has no steps
after its last state to show, and inventing some would be fabrication). The
episode is written by the recorder's ``build_episode``.

The import, by concern:

* ``files``: reading the HDF5 file and its demos (``read_demo_file``, ``read_demo``, ``DemoImportError``);
* ``tasks``: which task a file's env is, checked against ``--task`` and its robots (``task_for``);
* ``env``: the robosuite env of the file, reloaded from each demo's model XML (``ImportEnv``);
* ``replay``: the two replay modes and how exact they are (``replay``);
* ``ground_truth``: phases from simulator signals (``onset``, ``door_phases``, ``pick_phases``);
* ``importer``: one demo to an episode, and a file's demos into a fixture folder (``import_demo``,
  ``import_demos``).
"""

from vlmproprio.record.demos.env import ImportEnv, load_demo_model, make_import_env
from vlmproprio.record.demos.files import Demo, DemoFile, DemoImportError, read_demo, read_demo_file
from vlmproprio.record.demos.ground_truth import (
    closing_onset,
    descent_start,
    door_phases,
    label_steps,
    onset,
    pick_phases,
)
from vlmproprio.record.demos.importer import NO_SEED, episode_id_for, import_demo, import_demos
from vlmproprio.record.demos.replay import REPLAY_MODES, Replay, replay, replay_actions, replay_states
from vlmproprio.record.demos.tasks import SUPPORTED_ENVS, TASKS, task_for

__all__ = [
    "NO_SEED",
    "REPLAY_MODES",
    "SUPPORTED_ENVS",
    "TASKS",
    "Demo",
    "DemoFile",
    "DemoImportError",
    "ImportEnv",
    "Replay",
    "closing_onset",
    "descent_start",
    "door_phases",
    "episode_id_for",
    "import_demo",
    "import_demos",
    "label_steps",
    "load_demo_model",
    "make_import_env",
    "onset",
    "pick_phases",
    "read_demo",
    "read_demo_file",
    "replay",
    "replay_actions",
    "replay_states",
    "task_for",
]
