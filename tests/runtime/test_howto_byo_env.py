"""docs/howto/bring-your-own-env.md runs as written: its files (``# file: NAME`` on a code block's first line) are
written to a fresh directory and ``python train.py`` and ``python factories.py`` run there in real subprocesses:
make_vec over a custom Dict-observation env in its own module, SB3's PPO on top; and make_vec over env factories
defined in the script, mixed with an id."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).parents[2]
DOC = ROOT / "docs" / "howto" / "bring-your-own-env.md"


def _files() -> dict[str, str]:
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    files = {}
    for block in blocks:
        first, _, rest = block.partition("\n")
        m = re.fullmatch(r"# file: (\S+)", first)
        if m:
            files[m.group(1)] = block
    return files


def test_the_howto_runs_as_written(tmp_path: Path) -> None:
    files = _files()
    assert set(files) == {"my_envs.py", "train.py", "factories.py"}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    out = subprocess.run(
        [sys.executable, "train.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert lines[0].startswith("Dict(") and "steps_left" in lines[0]
    assert lines[1] == "{'goal': (4, 2), 'position': (4, 2), 'steps_left': (4,)}"
    assert lines[-2].startswith("rewards [") and "distance [" in lines[-2]
    assert lines[-1] == "done"
    out = subprocess.run(
        [sys.executable, "factories.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert lines[-1] == (
        "factories 4 (4, 2) ['<lambda>()', '<lambda>()', 'make_env.<locals>._make()', 'my_envs:DotToGoal-v0']"
    )
