"""Lazy package exports: a submodule loads only when one of its names is asked for; unknown names are clear errors."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_packages_import_their_heavy_submodules_only_on_demand() -> None:
    code = (
        "import sys, uniros_async.sim, uniros_async.training as t\n"
        "assert 'uniros_async.sim.servo' not in sys.modules and 'mujoco' not in sys.modules\n"
        "assert 'uniros_async.training.async_td3' not in sys.modules and 'torch' not in sys.modules\n"
        "t.TrainConfig\n"
        "assert 'uniros_async.training.config' in sys.modules and 'torch' not in sys.modules\n"
        "assert 'ServoSim' in dir(uniros_async.sim)\n"
        "uniros_async.sim.ServoSimConfig\n"
        "assert 'uniros_async.sim.servo' in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_unknown_name_is_an_attribute_error_naming_the_package() -> None:
    import uniros_async.training

    with pytest.raises(AttributeError, match=r"module 'uniros_async.training' has no attribute 'Nope'"):
        uniros_async.training.Nope  # noqa: B018


@pytest.mark.parametrize(
    "module", ["uniros_async", "uniros_async.transports", "uniros_async.transports.shm", "uniros_async.transports.tcp"]
)
def test_the_package_and_its_transports_import_no_gymnasium_mujoco_or_torch(module: str) -> None:
    code = (
        f"import sys, {module}\n"
        "heavy = ('gymnasium', 'mujoco', 'pinocchio', 'torch', 'stable_baselines3')\n"
        "assert not [m for m in heavy if m in sys.modules], [m for m in heavy if m in sys.modules]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("order", ["uniros_async first", "gymnasium first"])
def test_the_gymnasium_ids_are_registered_whichever_is_imported_first(order: str) -> None:
    imports = "import uniros_async, gymnasium" if order == "uniros_async first" else "import gymnasium, uniros_async"
    code = (
        f"{imports}\n"
        "spec = gymnasium.spec('uniros/Rx200Reach-v0')\n"
        "assert spec.entry_point == 'uniros_async.tasks.reach:ReachEnv', spec.entry_point\n"
        "assert 'SourceFileLoader' in type(gymnasium.__loader__).__name__, gymnasium.__loader__  # not our wrapper\n"
    )
    subprocess.run([sys.executable, "-W", "error", "-c", code], check=True, timeout=120)


@pytest.mark.slow
def test_the_core_runs_an_env_without_the_train_extra() -> None:
    """`pip install .` without extras has no torch, SB3, tensorboard, tqdm or matplotlib: an env still runs."""
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'stable_baselines3', 'tensorboard', 'tqdm', 'matplotlib'):\n"
        "            raise ModuleNotFoundError(f'No module named {name!r} (not installed without extras)')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import gymnasium as gym, uniros_async\n"
        "env = gym.make('uniros/Rx200Reach-v0', clock='sim')\n"
        "env.reset(seed=0)\n"
        "obs, reward, *_ = env.step(env.action_space.sample())\n"
        "env.close()\n"
        "assert obs.shape == (28,) and isinstance(reward, float), (obs.shape, reward)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
