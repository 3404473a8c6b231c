"""``uniros train`` killed with SIGKILL at several moments, one of them in the middle of a checkpoint write, resumes
with ``--resume`` from the last complete checkpoint and finishes the run with the step count continuing.

Real ``uniros train`` subprocesses on a tiny accelerated config (sim clock, a 32x32 TD3, a checkpoint every 40
steps), one torch thread.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

TOTAL_STEPS = 360
CONFIG = f"""\
name: crash
seed: 0
total_steps: {TOTAL_STEPS}
torch_threads: 1
envs:
  - {{id: uniros/Rx200Reach-v0, kwargs: {{clock: sim}}}}
td3: {{learning_starts: 40, buffer_size: 5000, net_arch: [32, 32], batch_size: 32}}
eval: {{every_steps: 100000, episodes: 1}}
checkpoint: {{every_steps: 40, keep: 2}}
"""


def _start(*args: str, log: Path) -> subprocess.Popen[bytes]:
    with open(log, "ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "uniros_async.cli", "train", *args, "--no-progress"],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: the kill below reaches nothing else
        )


def _latest_step(run: Path) -> int:
    root = run / "checkpoints"
    if not (root / "latest").is_file():
        return -1
    name = (root / "latest").read_text().strip()
    return json.loads((root / name / "meta.json").read_text())["step"] if (root / name).is_dir() else -1


def _kill_when(proc: subprocess.Popen[bytes], cond: Callable[[], bool], what: str, log: Path) -> None:
    deadline = time.monotonic() + 120
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"train exited ({proc.returncode}) before {what}:\n{log.read_text()[-3000:]}")
        assert time.monotonic() < deadline, f"no {what} within 120 s"
        time.sleep(0.001)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)


def _children_gone(pgid: int) -> bool:
    """No process of the killed run's group is left (its env workers, if any, follow it)."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    return False


def _check_intact(run: Path) -> int:
    """``latest`` names a complete checkpoint; returns its step."""
    root = run / "checkpoints"
    name = (root / "latest").read_text().strip()
    for f in ("model.zip", "meta.json", "replay_buffer.pkl"):
        assert (root / name / f).is_file(), f"{name} lacks {f}"
    return int(json.loads((root / name / "meta.json").read_text())["step"])


def test_sigkill_at_any_moment_resumes_from_the_last_complete_checkpoint(tmp_path: Path) -> None:
    cfg = tmp_path / "crash.yaml"
    cfg.write_text(CONFIG)
    run = tmp_path / "run"
    log = tmp_path / "train.log"
    root = run / "checkpoints"

    def writing() -> bool:  # a checkpoint's temporary directory exists: a write is under way
        if not root.is_dir():
            return False
        with os.scandir(root) as it:
            return any(p.name.startswith(".tmp-") for p in it)

    # 1. killed between checkpoints, just after the first one landed
    proc = _start(str(cfg), "--run-dir", str(run), log=log)
    _kill_when(proc, lambda: _latest_step(run) >= 40, "a first checkpoint", log)
    assert _children_gone(proc.pid)
    first = _check_intact(run)

    # 2. resumed, then killed in the middle of a checkpoint write
    proc = _start(str(cfg), "--run-dir", str(run), "--resume", log=log)
    _kill_when(proc, lambda: _latest_step(run) > first and writing(), "a checkpoint write after resuming", log)
    assert _children_gone(proc.pid)
    second = _check_intact(run)
    assert second > first  # the resumed run went on from the first checkpoint and wrote more

    # 3. resumed again (from the run's own config.yaml), killed mid-write once more
    proc = _start("--run-dir", str(run), "--resume", log=log)
    _kill_when(proc, lambda: _latest_step(run) > second and writing(), "a second checkpoint write", log)
    third = _check_intact(run)
    assert third > second

    # 4. resumed to the end
    done = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "train", "--run-dir", str(run), "--resume", "--no-progress"],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"done: {TOTAL_STEPS} steps" in done.stdout
    assert _check_intact(run) == TOTAL_STEPS
    assert not [p for p in root.iterdir() if p.name.startswith(".")]  # nothing half-written left behind
    with open(run / "episodes.csv", newline="") as f:
        steps = [int(float(r["step"])) for r in csv.DictReader(f)]
    assert steps == sorted(steps), "episode rows after a resume continue the step count"
    assert steps and steps[-1] <= TOTAL_STEPS


def test_clean_partial_puts_back_a_checkpoint_whose_rewrite_never_landed(tmp_path: Path) -> None:
    from uniros_async.training.checkpoint import clean_partial, latest_checkpoint

    root = tmp_path / "checkpoints"
    moved = root / ".old-step_000000080-4242"  # a rewrite of step 80 was killed between its two renames
    kept = root / ".old-step_000000040-4242"  # a rewrite of step 40 that did land: the old copy is garbage
    for d in (moved, kept, root / "step_000000040", root / ".tmp-step_000000120-4242"):
        d.mkdir(parents=True)
        (d / "model.zip").write_bytes(b"zip")
        (d / "meta.json").write_text("{}")
    (root / "latest").write_text("step_000000080\n")
    (root / ".latest.tmp").write_text("step_000000120\n")
    clean_partial(tmp_path)
    assert sorted(p.name for p in root.iterdir()) == ["latest", "step_000000040", "step_000000080"]
    assert latest_checkpoint(tmp_path) == root / "step_000000080"
