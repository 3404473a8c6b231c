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
