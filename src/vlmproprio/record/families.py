"""robosuite envs, success checks and instructions of the catalog's task families (record/catalog.json).

The shipped 22 episodes keep their own set-up (``scenes.make_env``): nothing here may change them. New
episodes use robosuite's own placement initialiser, its ranges widened as the catalog says, drawn with the
env's seeded generator, and our cameras where robosuite's frame a task badly:

* ``vlmproprio_bins`` (pick-place, see ``scenes``);
* ``vlmproprio_table`` (Stack): above the table's far edge, facing the robot, so the cubes are never behind
  the arm; image left/right are the robot's right/left, and every episode stores its camera's axes
  (extra.camera_axes) so that the rubric reads image words in this camera's terms.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from vlmproprio.record import scenes
from vlmproprio.record.catalog import Family, SlotPlan

TABLE_CAMERA = "vlmproprio_table"
# Placed by eye: above the far edge of the table, looking down and back at the cubes and the robot (from behind
# the robot, the arm hides the cubes). Image right is the robot's left: the episodes store the camera axes.
TABLE_CAMERA_POS = (0.62, 0.0, 1.6)
TABLE_CAMERA_TARGET = (-0.06, 0.0, 0.86)
TABLE_CAMERA_FOVY = 42.0

STACK_PHASES = ("approach", "descend", "grasp", "lift", "transport to the green cube", "lower", "release", "retreat")


def _camera(name: str, pos, target, fovy: float):
    from robosuite.utils.mjcf_utils import array_to_string, new_element

    return new_element(
        tag="camera",
        name=name,
        pos=array_to_string(pos),
        quat=array_to_string(scenes.lookat_quat_wxyz(pos, target)),
        fovy=str(fovy),
    )


@cache
def _env_class(env_name: str, placement: tuple, camera: str):
    """A subclass of robosuite's env with the catalog's placement ranges and our camera added to the model.

    A subclass, not a patched instance: robosuite rebuilds the model on hard resets and keeps both."""
    import robosuite

    base = robosuite.environments.REGISTERED_ENVS[env_name]

    def _load_model(self):
        base._load_model(self)
        for attr, value in placement:
            setattr(self.placement_initializer, attr, value)
        if camera == scenes.BIN_CAMERA:
            self.model.worldbody.append(scenes.bin_camera_element())
        elif camera == TABLE_CAMERA:
            self.model.worldbody.append(_camera(TABLE_CAMERA, TABLE_CAMERA_POS, TABLE_CAMERA_TARGET, TABLE_CAMERA_FOVY))

    return type(f"{env_name}Vlmproprio", (base,), {"_load_model": _load_model})


def env_name(plan: SlotPlan) -> str:
    """The robosuite env an episode names: PickPlaceMilk for a pick-place of the milk carton, as robosuite does."""
    if plan.family.env == "PickPlace":
        return "PickPlace" + str(plan.obj.robosuite).capitalize()
    return plan.family.env


def task_info(plan: SlotPlan) -> scenes.TaskInfo:
    fam = plan.family
    return scenes.TaskInfo(fam.task, env_name(plan), fam.camera, plan.obj.name, fam.action)


def make_env(plan: SlotPlan, seed: int, horizon: int):
    """A fresh env for one attempt of a slot, reset and with robosuite's ghost objects hidden."""
    fam: Family = plan.family
    kwargs = scenes.env_kwargs(seed, horizon)
    if fam.env == "PickPlace":
        kwargs |= {"single_object_mode": 2, "object_type": plan.obj.robosuite}
    env = _env_class(fam.env, fam.placement, fam.camera)(**kwargs)
    env.reset()
    scenes.hide_ghosts(env)
    return env


def instruction(plan: SlotPlan) -> str:
    fam = plan.family
    if fam.task == "stack":
        return "Pick up the red cube and stack it on the green cube."
    return scenes.instruction(task_info(plan), plan.bin_index)


def cube_pos(env, which: str) -> np.ndarray:
    return env.sim.data.body_xpos[getattr(env, f"{which}_body_id")].copy()


def stack_success(env, moved_recently_m: float) -> bool:
    """The red cube resting on the green one with the gripper open and away (robosuite's check, plus at rest)."""
    a, b = cube_pos(env, "cubeA"), cube_pos(env, "cubeB")
    away = np.linalg.norm(scenes.grip_pos(env) - a) > 0.04
    on_top = np.linalg.norm(a[:2] - b[:2]) < 0.03 and 0.035 < a[2] - b[2] < 0.06
    return bool(env._check_success()) and bool(on_top and away) and moved_recently_m < 0.002


def tracked_object(env, plan: SlotPlan) -> np.ndarray:
    """The position of the object the task moves (pick-place: robosuite's object; Stack: the red cube)."""
    if plan.family.task == "stack":
        return cube_pos(env, "cubeA")
    return scenes.object_pos(env)
