"""The gymnasium ids of uniros_async, registered on ``import uniros_async`` without importing the tasks.

Entry points are strings, so registering costs one gymnasium import; MuJoCo, pinocchio and the env code load
only when an env is made (a transport-only process or a spawned worker does not pay for them).
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

__all__ = ["ENV_IDS", "register_envs"]

ENV_IDS: dict[str, tuple[str, str]] = {
    "uniros/Rx200Reach-v0": ("rx200", "uniros_async.tasks.reach:ReachEnv"),
    "uniros/Rx200ReachGoal-v0": ("rx200", "uniros_async.tasks.reach:ReachGoalEnv"),
    "uniros/Ned2Reach-v0": ("ned2", "uniros_async.tasks.reach:ReachEnv"),
    "uniros/Ned2ReachGoal-v0": ("ned2", "uniros_async.tasks.reach:ReachGoalEnv"),
}


def register_envs() -> None:
    """Register every id (idempotent); all have ``max_episode_steps=100``."""
    for env_id, (arm, entry_point) in ENV_IDS.items():
        if env_id in registry:
            continue
        register(
            id=env_id,
            entry_point=entry_point,
            max_episode_steps=100,
            kwargs={"arm": arm},
            disable_env_checker=True,  # step() validates actions itself; the tests run the full checkers
        )
