"""The robosuite tasks as the recorder and the demo importer set them up: environment, camera, success.

The recorder records the paper's two tasks (Door, PickPlaceCereal); the demo importer
(``vlmproprio.record.demos``) also brings in PickPlaceCan and Lift demonstrations.

Cameras (chosen by eye from contact sheets, see docs/fixtures.md):

* Door: robosuite's ``sideview`` shows the door face-on with the lever and the
  arm in profile (``agentview``/``frontview`` frame the door edge-on).
* PickPlaceCereal: a camera added by us, ``vlmproprio_bins``, above and behind
  the robot looking down at both bins. All four compartments of the target bin
  are visible, the near row (close to the robot) is the bottom row of the image,
  and image left/right equal the robot's left/right, so "near-left" means the
  same thing to the robot, the image and the caption. robosuite's ``agentview``
  looks at the robot from the front, which mirrors left/right and puts the near
  row at the back.

The translucent "ghost" objects robosuite draws in the target bin (``Visual*``
bodies, one per object type, with the cereal ghost in compartment 2 in every
episode) are made fully transparent before any frame is rendered: a captioner
must not see a box in compartment 2 when the real one goes elsewhere.

* PickPlaceCan: the same arena and bin camera as PickPlaceCereal (the camera is
  injected into an imported demo's model XML, see ``with_bin_camera``).
* Lift: robosuite's ``sideview`` shows the arm and the cube in profile, so the
  lift is a vertical motion in the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from vlmproprio.episodes import TargetBin

STEP_STRIDE = 20
IMAGE_SIZE = 256
CONTROL_FREQ = 20
BIN_CAMERA = "vlmproprio_bins"
DOOR_CAMERA = "sideview"
LIFT_CAMERA = "sideview"
# Placed by eye: above and behind the robot base (x=-0.56), looking down at the middle between the bins.
BIN_CAMERA_POS = (-0.25, 0.02, 2.38)
BIN_CAMERA_TARGET = (0.1, 0.02, 0.8)
BIN_CAMERA_FOVY = 45.0

# robosuite's PickPlace.not_in_bin indexing: bit 0 of the index = far (x > bin centre), bit 1 = robot's left
# (y > bin centre, away from the source bin). In the bin camera's image the robot's left is the image's left.
COMPARTMENT_WORDS = {0: ("near", "right"), 1: ("far", "right"), 2: ("near", "left"), 3: ("far", "left")}

DOOR_PHASES = ("approach", "grasp handle", "turn handle down", "pull door open", "release and retreat")


LIFT_PHASES = ("approach", "descend", "grasp", "lift", "release", "retreat")


def bin_phases(index: int) -> tuple[str, ...]:
    return ("approach", "descend", "grasp", "lift", f"transport to bin {index}", "lower", "release", "retreat")


@dataclass(frozen=True)
class TaskInfo:
    """Metadata written into every episode of a task."""

    task: str
    env_name: str
    camera: str
    target_object: str
    action: str


DOOR = TaskInfo("door", "Door", DOOR_CAMERA, "door handle", "open the door")
PICK_PLACE = TaskInfo("pick_place", "PickPlaceCereal", BIN_CAMERA, "cereal box", "pick and place")
# Only imported (no scripted operator): see vlmproprio.record.demos.
PICK_PLACE_CAN = TaskInfo("pick_place", "PickPlaceCan", BIN_CAMERA, "can", "pick and place")
LIFT = TaskInfo("lift", "Lift", LIFT_CAMERA, "cube", "lift")


def target_bin(index: int) -> TargetBin:
    if index not in COMPARTMENT_WORDS:
        raise ValueError(f"bin index must be 0-3, got {index}")
    row, side = COMPARTMENT_WORDS[index]
    next_to = "next to the source bin" if side == "right" else "away from the source bin"
    return TargetBin(
        index=index,
        row=row,
        side=side,
        description=f"the {row}-{side} compartment of the target bin ({row} {'to' if row == 'near' else 'from'} "
        f"the robot, {next_to}; {'bottom' if row == 'near' else 'top'}-{side} in the image)",
    )


def instruction(task: TaskInfo, bin_index: int | None = None) -> str:
    """The instruction a correct final caption should amount to (for people reading reports)."""
    if task.task == "door":
        return "Grasp the door handle, turn it down, and pull the door open toward the robot."
    if task.task == "lift":
        return f"Grasp the {task.target_object} on the table and lift it up."
    tb = target_bin(bin_index)
    return (
        f"Pick up the {task.target_object} from the source bin and place it in the {tb.row}-{tb.side} compartment "
        "of the target bin."
    )


def lookat_quat_wxyz(pos, target) -> np.ndarray:
    """MuJoCo camera orientation (w, x, y, z) looking from ``pos`` at ``target`` with the world z axis up."""
    from scipy.spatial.transform import Rotation

    forward = np.asarray(target, float) - np.asarray(pos, float)
    z = -forward / np.linalg.norm(forward)  # MuJoCo cameras look along their -z axis
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    q = Rotation.from_matrix(np.stack([x, y, z], axis=1)).as_quat()  # x, y, z, w
    return np.array([q[3], q[0], q[1], q[2]])


def bin_camera_element():
    """The MJCF <camera> element of our bin camera (also injected into imported demos' model XML)."""
    from robosuite.utils.mjcf_utils import array_to_string, new_element

    return new_element(
        tag="camera",
        name=BIN_CAMERA,
        pos=array_to_string(BIN_CAMERA_POS),
        quat=array_to_string(lookat_quat_wxyz(BIN_CAMERA_POS, BIN_CAMERA_TARGET)),
        fovy=str(BIN_CAMERA_FOVY),
    )


def with_bin_camera(xml: str) -> str:
    """A model XML with our bin camera at the end of its worldbody (unchanged when it already has it).

    Only text is added: every other attribute keeps its exact string, so the compiled physics is unchanged."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml)
    if any(cam.get("name") == BIN_CAMERA for cam in root.iter("camera")):
        return xml
    worldbody = root.find("worldbody")
    if worldbody is None:
        raise ValueError("model XML has no <worldbody>")
    worldbody.append(bin_camera_element())
    return ET.tostring(root, encoding="unicode")


@cache
def _pick_place_class():
    """PickPlaceCereal with our bin camera added to the arena (a subclass, so hard resets keep it)."""
    from robosuite.environments.manipulation.pick_place import PickPlaceCereal

    class PickPlaceCerealBinCamera(PickPlaceCereal):
        def _load_model(self):
            super()._load_model()
            # The task model has already merged the arena, so the camera goes into the task's worldbody.
            self.model.worldbody.append(bin_camera_element())

    return PickPlaceCerealBinCamera


def env_kwargs(seed: int, horizon: int) -> dict:
    """robosuite constructor arguments of every env the recorder and the importer make."""
    return dict(
        robots="Panda",
        has_renderer=False,
        has_offscreen_renderer=True,
        use_camera_obs=False,  # rendering every step would triple the time; the recorder renders sampled steps
        control_freq=CONTROL_FREQ,
        horizon=horizon,
        ignore_done=True,
        hard_reset=False,
        seed=seed,
    )


def make_env(task: TaskInfo, seed: int, horizon: int):
    """A fresh robosuite env for one episode (a new env per episode keeps episodes independent)."""
    import robosuite as suite

    kwargs = env_kwargs(seed, horizon)
    env = suite.make("Door", **kwargs) if task.task == "door" else _pick_place_class()(**kwargs)
    env.reset()
    hide_ghosts(env)
    return env


def hide_ghosts(env) -> int:
    """Make robosuite's translucent target-bin ghost objects invisible; returns how many geoms were hidden."""
    m = env.sim.model
    hidden = 0
    for g in range(m.ngeom):
        body = m.body_id2name(int(m.geom_bodyid[g])) or ""
        if body.startswith("Visual"):
            m.geom_rgba[g, 3] = 0.0
            hidden += 1
    return hidden


def camera_axes(env, camera: str) -> dict[str, list[float]]:
    """Image right, image up and viewing direction of a camera as unit vectors in the world (= robot) frame.

    Written into imported episodes (episode.json extra.camera_axes) so the rubric reads image words such as
    left/right in that camera's terms; the shipped cameras' axes are in vlmproprio/lexicons/cameras.json."""
    m, d = env.sim.model, env.sim.data
    mat = np.asarray(d.cam_xmat[m.camera_name2id(camera)]).reshape(3, 3)  # columns: camera x, y, z
    return {
        k: [round(float(v), 3) for v in vec]
        for k, vec in (("right", mat[:, 0]), ("up", mat[:, 1]), ("view", -mat[:, 2]))
    }


def render(env, camera: str, size: int = IMAGE_SIZE) -> np.ndarray:
    # MuJoCo's offscreen buffer is bottom-up; flip so row 0 is the top of the image.
    return np.ascontiguousarray(env.sim.render(width=size, height=size, camera_name=camera)[::-1])


# ---------------------------------------------------------------------------------------------- success


def door_hinge(env) -> float:
    return float(env.sim.data.qpos[env.sim.model.get_joint_qpos_addr("Door_hinge")])


def door_latch(env) -> float:
    """The lever's turn (rad, positive = down); 0 when the door has no latch (robosuite's ``use_latch=False``)."""
    m = env.sim.model
    if "Door_latch_joint" not in m.joint_names:
        return 0.0
    return float(env.sim.data.qpos[m.get_joint_qpos_addr("Door_latch_joint")])


def door_success(env) -> bool:
    return bool(env._check_success())  # hinge opened past robosuite's success angle (0.3 rad)


def object_pos(env) -> np.ndarray:
    """World position of the task's object: PickPlace's chosen object, or Lift's cube."""
    if hasattr(env, "cube_body_id"):
        return env.sim.data.body_xpos[env.cube_body_id].copy()
    obj = env.objects[env.object_id]
    return env.sim.data.body_xpos[env.obj_body_id[obj.name]].copy()


def grip_pos(env) -> np.ndarray:
    """World position of the grip site (the point between the fingertips)."""
    return env.sim.data.site_xpos[env.robots[0].eef_site_id["right"]].copy()


def in_compartment(env, index: int) -> bool:
    """The object inside compartment ``index`` (robosuite's own check only knows compartment 2)."""
    return not env.not_in_bin(object_pos(env), index)


def bin_success(env, index: int, moved_recently_m: float) -> bool:
    """Cereal at rest inside the chosen compartment with the gripper away from it.

    "At rest" is judged from the box's displacement over the last frame interval (``moved_recently_m``):
    MuJoCo's contact solver makes the box's instantaneous velocity jitter at ~2 cm/s while it stands still."""
    grip = env.sim.data.site_xpos[env.robots[0].eef_site_id["right"]]
    away = np.linalg.norm(grip - object_pos(env)) > 0.05
    return in_compartment(env, index) and moved_recently_m < 0.002 and bool(away)
