"""Workers start from anywhere: ``make_vec`` from a script without ``if __name__ == "__main__":``, from code piped
to ``python -``, and with an env registered by the script itself (its class in a module next to the script). Real
interpreters in real subprocesses; each prints what its workers returned and the test checks it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

MODULE = '''
import os
from gymnasium.envs.classic_control.cartpole import CartPoleEnv


class PidCartPole(CartPoleEnv):
    """CartPole whose step says which process stepped it."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated, {**info, "pid": os.getpid()}
'''

# No main guard: with multiprocessing's spawn every worker would run this script again.
SCRIPT = """
import os
import gymnasium as gym
import numpy as np
import script_envs
from uniros_async.runtime import make_vec

gym.register("ScriptPidCartPole-v0", entry_point=script_envs.PidCartPole, max_episode_steps=20)
venv = make_vec(["ScriptPidCartPole-v0", "CartPole-v1"])
obs, _ = venv.reset(seed=0)
_, reward, _, _, info = venv.step(np.array([0, 1]))
print("pids", os.getpid(), *venv.pids)
print("stepped", int(info["pid"][0]), obs.shape, reward.tolist())
venv.close()
print("done")
"""


def _run(args: list[str], cwd: Path, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[2]), os.environ.get("PYTHONPATH", "")]),
    }
    return subprocess.run(args, cwd=cwd, input=stdin, capture_output=True, text=True, timeout=120, env=env)


def test_make_vec_from_a_script_without_a_main_guard(tmp_path: Path) -> None:
    (tmp_path / "script_envs.py").write_text(MODULE)
    (tmp_path / "run.py").write_text(SCRIPT)
    out = _run([sys.executable, str(tmp_path / "run.py")], cwd=Path("/"))  # the script's dir is not the cwd
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if " " in line)
    me, *workers = (int(p) for p in lines["pids"].split())
    assert len(workers) == 2 and me not in workers
    stepped = lines["stepped"].split(" ", 1)
    assert int(stepped[0]) == workers[0]  # the script's env ran in the first worker
    assert "(2, 4)" in stepped[1] and "[1.0, 1.0]" in stepped[1]
    assert out.stdout.splitlines()[-1] == "done"
    assert out.stdout.count("pids") == 1  # the script ran once: no worker re-ran it


def test_make_vec_from_code_piped_to_python_stdin(tmp_path: Path) -> None:
    code = textwrap.dedent("""
        import numpy as np
        from uniros_async.runtime import make_vec
        venv = make_vec(["CartPole-v1"] * 2)
        obs, _ = venv.reset(seed=0)
        _, reward, _, _, _ = venv.step(np.array([0, 1]))
        print("ok", obs.shape, reward.tolist())
        venv.close()
    """)
    out = _run([sys.executable, "-"], cwd=tmp_path, stdin=code)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok (2, 4) [1.0, 1.0]"


def test_an_env_class_defined_in_main_is_refused_with_what_to_do(tmp_path: Path) -> None:
    code = textwrap.dedent("""
        import gymnasium as gym
        from gymnasium.envs.classic_control.cartpole import CartPoleEnv
        from uniros_async.errors import ConfigError
        from uniros_async.runtime import make_vec

        class MainCartPole(CartPoleEnv):
            pass

        gym.register("MainCartPole-v0", entry_point=MainCartPole)
        try:
            make_vec(["MainCartPole-v0"])
        except ConfigError as exc:
            print("refused:", exc)
    """)
    out = _run([sys.executable, "-"], cwd=tmp_path, stdin=code)
    assert out.returncode == 0, out.stderr
    assert "refused:" in out.stdout and "__main__" in out.stdout and "module" in out.stdout


PROBE_MODULE = '''
import sys
import gymnasium as gym
from gymnasium.envs.classic_control.cartpole import CartPoleEnv


class ProbeCartPole(CartPoleEnv):
    """CartPole that tells which of the given modules its worker has loaded."""

    def loaded(self, *names):
        return [n for n in names if n in sys.modules]


gym.register("ProbeCartPole-v0", entry_point=ProbeCartPole, max_episode_steps=20)
'''


def test_a_gymnasium_env_worker_loads_neither_pydantic_nor_the_agent_side(tmp_path: Path) -> None:
    """What a worker of a plain gymnasium env imports: the env, gymnasium and the protocol, not the config models
    (pydantic), PyYAML, uniros's env classes or the supervisor and vector env (the agent side)."""
    (tmp_path / "probe_envs.py").write_text(PROBE_MODULE)
    heavy = [
        "pydantic",
        "yaml",
        "uniros_async.envs.base",
        "uniros_async.runtime.supervisor",
        "uniros_async.runtime.vector",
        "uniros_async.bus.node",
    ]
    code = textwrap.dedent(f"""
        from uniros_async.runtime import make_vec
        venv = make_vec(["probe_envs:ProbeCartPole-v0"])
        print("worker", venv.call("loaded", *{heavy!r})[0])
        print("probe", venv.call("loaded", "gymnasium", "uniros_async.runtime.worker")[0])
        venv.close()
    """)
    out = _run([sys.executable, "-"], cwd=tmp_path, stdin=code)
    assert out.returncode == 0, out.stderr
    assert "worker []" in out.stdout  # none of them
    assert "probe ['gymnasium', 'uniros_async.runtime.worker']" in out.stdout  # the probe itself works


def test_bad_kwargs_fail_in_the_caller_and_stop_the_interpreters_started_meanwhile() -> None:
    """The workers' interpreters start while the caller checks the env arguments; a bad one is reported from the
    caller with the key's path, and no interpreter outlives the error (none was given an env)."""
    from _children import children

    from uniros_async.errors import ConfigError
    from uniros_async.runtime import make_vec

    with pytest.raises(ConfigError, match="reward_type") as e:
        make_vec(["uniros/Rx200Reach-v0"] * 2, clock="sim", reward_type="spars")
    assert "did you mean 'sparse'?" in str(e.value)
    assert children() == []


def test_an_interpreter_started_early_is_told_the_environment_set_since(monkeypatch: pytest.MonkeyPatch) -> None:
    """What the agent's checks set in the environment while an interpreter was already starting (an imported module
    may set ``MUJOCO_GL``) goes into the spec's ``environ``; stopped before it had a spec, the interpreter exits."""
    from uniros_async.runtime.launch import start_interpreter

    proc, conn = start_interpreter()
    try:
        assert proc.environ_changes() == {}
        monkeypatch.setenv("UNIROS_TEST_SET_DURING_CHECKS", "egl")
        assert proc.environ_changes() == {"UNIROS_TEST_SET_DURING_CHECKS": "egl"}
    finally:
        conn.close()
        proc.discard()
    assert proc.exitcode is not None
