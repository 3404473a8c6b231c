"""``uniros train|eval|plot`` as a user runs them (real subprocesses): SIGTERM keeps the last checkpoint and
``--resume`` continues from it; eval prints the three figures; plot writes a PNG; bad input exits 2 at once."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

SMOKE = Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml"
# deadlines, not expected times: a few hundred steps take seconds, but a suite on 2 cores can slow them severalfold
LOADED_S = 300.0


def uniros(*args: str, timeout_s: float = LOADED_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", *args], capture_output=True, text=True, timeout=timeout_s
    )


def test_train_sigterm_resume_eval_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "smoke"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "uniros_async.cli",
            "train",
            str(SMOKE),
            "--run-dir",
            str(run),
            "--steps",
            "100000",
            "--no-progress",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + LOADED_S
        while not (run / "checkpoints" / "latest").exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"no checkpoint within {LOADED_S:.0f} s"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=LOADED_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "interrupted at step" in err and "--resume" in err
    assert "(signal 15);" in err, err  # what stopped it, named
    assert "Task was destroyed but it is pending" not in err  # the interrupted step's task was cancelled
    latest = (run / "checkpoints" / "latest").read_text().strip()
    assert (run / "checkpoints" / latest / "model.zip").is_file()
    assert not [p for p in (run / "checkpoints").iterdir() if p.name.startswith(".tmp")]

    done = uniros("train", "--resume", "--run-dir", str(run), "--steps", "300", "--no-progress")
    assert done.returncode == 0, done.stderr
    assert "done: 300 steps" in done.stdout and "success rate" in done.stdout

    ev = uniros(
        "eval",
        str(run),
        "--env",
        "uniros/Rx200Reach-v0",
        "--robot",
        "emulated-real",
        "--episodes",
        "2",
        "--no-progress",
    )
    assert ev.returncode == 0, ev.stderr
    assert "success rate:" in ev.stdout and "mean return:" in ev.stdout and "mean episode length:" in ev.stdout
    assert "observations: as the env gives them (trained without normalize_obs)" in ev.stdout

    from uniros_async.cli import main

    png = tmp_path / "curves.png"
    assert main(["plot", str(run), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    task = (run / "episodes.csv").read_text().splitlines()[1].split(",")[1]
    one = tmp_path / "one.png"
    assert main(["plot", str(run), "--out", str(one), "--tasks", task]) == 0 and one.exists()
    assert main(["plot", str(run), "--out", str(one), "--tasks", "ned2_nowhere"]) == 2
    assert f"--tasks: no run has ['ned2_nowhere']; the runs' tasks are ['{task}']" in capsys.readouterr().err


def test_bad_input_exits_2_before_anything_starts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from uniros_async.cli import main

    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nenvs: [uniros/Rx200Reach-v0]\ntd3: {gama: 0.9}\n")
    assert main(["train", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err == f"uniros: error: {bad}: td3.gama: unknown key; did you mean 'gamma'?\n"
    assert not Path("runs/x").exists()
    run = tmp_path / "r"
    argv = ["train", "--env", "uniros/Rx200Reach-v0", "--env-kwargs", "{reward: dense}", "--run-dir", str(run)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "envs[0].kwargs.reward: unknown keyword argument; did you mean 'reward_type'?" in err and not run.exists()
    assert main(["train", "--env", "uniros/Rx200Reach-v0", "--set", "td3.tau=3", "--run-dir", str(run)]) == 2
    assert "command line: td3.tau: must be <= 1, got 3" in capsys.readouterr().err and not run.exists()
    assert main(["train", "--env", "uniros/Rx200Reach-v0", "--set", "td3.batch_size=128.5", "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    assert "command line: td3.batch_size: expected an integer, got 128.5" in err and not run.exists()
    assert main(["eval", str(tmp_path), "--env", "uniros/Rx200Reach-v0"]) == 2
    assert "no checkpoint at" in capsys.readouterr().err
    assert main(["plot", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err
