"""acme_arms: a user's own package that adds an arm, a placement, a task and its ids, and a ROS driver to uniros_async.

Nothing here edits uniros_async: importing this package registers everything, as a gymnasium plugin registers
its envs. ``gymnasium.make("acme_arms:acme/Acme5Reach-v0")`` (or ``make_vec`` with that id) imports it first, in
the caller and in every worker.
"""

from __future__ import annotations

from acme_arms.robot import ACME5
from uniros_async import register_env_id, register_placement, register_robot, register_task
from uniros_async.adapters.drivers import register_ros_driver

__all__ = ["ACME5", "GOAL_MAX", "GOAL_MIN"]

# the arm: its spec and MJCF model live in this package
register_robot(ACME5)

# a placement: the in-process servo sim, wrapped (acme_arms/placement.py); built by entry point, imported when used
register_placement(
    "acme-sim",
    "acme_arms.placement:open_acme_sim",
    can_teleport=True,  # it is a nominal sim: reset() may put the arm home at once
    sim_clock=True,  # it runs in the env's process, so clock="sim" works
    stamps_on_env_clock=True,
    start_timeout_s=30.0,
    description="the servo sim in the env's process, counted",
)

# task ids: uniros_async's reach tasks on this arm, with a goal box that suits it
GOAL_MIN = (0.15, -0.15, 0.05)
GOAL_MAX = (0.25, 0.15, 0.25)
register_env_id("acme5", "Reach", env_id="acme/Acme5Reach-v0", kwargs={"goal_min": GOAL_MIN, "goal_max": GOAL_MAX})
register_env_id(
    "acme5", "ReachGoal", env_id="acme/Acme5ReachGoal-v0", kwargs={"goal_min": GOAL_MIN, "goal_max": GOAL_MAX}
)

# a task of this package: the reach env with a sparse reward by default, on this arm and on uniros_async's rx200
register_task("ReachSparse", "uniros_async.tasks.reach:ReachEnv", kwargs={"reward_type": "sparse"})
register_env_id(
    "acme5", "ReachSparse", env_id="acme/Acme5ReachSparse-v0", kwargs={"goal_min": GOAL_MIN, "goal_max": GOAL_MAX}
)
register_env_id("rx200", "ReachSparse", env_id="acme/Rx200ReachSparse-v0")

# its ROS 1 driver's topics, so robot="ros1://HOST:PORT" needs no settings for it
register_ros_driver(
    "ros1",
    "acme5",
    driver="ros_control",
    joint_states="/joint_states",
    command="/arm_controller/command",
    command_type="trajectory_msgs/JointTrajectory",
)
