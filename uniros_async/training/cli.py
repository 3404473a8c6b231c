"""``uniros train``, ``uniros eval`` and ``uniros plot`` (registered by uniros_async/cli.py).

    uniros train CONFIG.yaml [--resume] [--run-dir DIR] [--steps N] [--seed S] [--set KEY=VALUE ...]
    uniros train --env uniros/Rx200Reach-v0 --steps 10000 [--env-kwargs '{reward_type: dense}']
    uniros train --resume --run-dir runs/NAME            (the run's own config.yaml)
    uniros eval CHECKPOINT --env ID [--robot emulated-real] [--env-kwargs YAML] --episodes 200 [--json PATH]
    uniros eval CHECKPOINT --env ID --sweep [--sweep-knobs all backlash ...] [--strengths 0 1 3] --json PATH --plot PNG
    uniros plot RUN_DIR [RUN_DIR ...] [--out PNG] [--labels ...] [--x steps|minutes]

``main`` functions take parsed values, not argparse (house style: the bench CLI keeps ``main(config)`` apart).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

import yaml

from uniros_async.errors import ConfigError
from uniros_async.yamlio import loads_yaml

__all__ = ["add_parsers", "run"]

logger = logging.getLogger(__name__)


def add_parsers(subparsers: Any) -> None:
    """Add ``train``, ``eval`` and ``plot`` to the ``uniros`` subparsers."""
    t = subparsers.add_parser("train", help="train TD3 / TD3+HER (single or multi-task) from a YAML config")
    t.add_argument("config", nargs="?", default=None, help="YAML TrainConfig (see configs/)")
    t.add_argument("--resume", action="store_true", help="continue from the run's last checkpoint")
    t.add_argument("--run-dir", default=None, help="run directory (default runs/NAME)")
    t.add_argument("--name", default=None, help="run name")
    t.add_argument("--env", action="append", default=None, metavar="ID", help="train env id (repeat: multi-task)")
    t.add_argument(
        "--env-kwargs", default=None, metavar="YAML", help="kwargs for every --env, e.g. '{reward_type: sparse}'"
    )
    t.add_argument("--steps", type=int, default=None, help="total env steps")
    t.add_argument("--seed", type=int, default=None, help="the run's seed (default: the config's)")
    t.add_argument(
        "--learner",
        choices=("sync", "async"),
        default=None,
        help="SB3's TD3 or the asynchronous learner (default: the config's)",
    )
    t.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key (dotted; YAML value), e.g. --set td3.batch_size=128",
    )
    t.add_argument("--no-progress", action="store_true", help="no progress bar")

    e = subparsers.add_parser("eval", help="success rate, mean return and episode length of a checkpoint")
    e.add_argument("checkpoint", help="run directory, checkpoint directory or model.zip")
    e.add_argument("--env", required=True, metavar="ID", help="env id, e.g. uniros/Rx200Reach-v0")
    e.add_argument(
        "--env-kwargs",
        default=None,
        metavar="YAML",
        help="env kwargs as YAML, e.g. '{reward_type: dense}' (default: those the policy was trained with "
        "on this env id)",
    )
    e.add_argument("--robot", default=None, help="sim, emulated-real, ... (shortcut for the robot kwarg)")
    e.add_argument(
        "--clock", default="sim", choices=("sim", "wall"), help="sim: accelerated (default); wall: real time"
    )
    e.add_argument("--episodes", type=int, default=200, help="episodes to run (default %(default)s)")
    e.add_argument("--seed", type=int, default=0, help="seeds the env and its goals (default %(default)s)")
    e.add_argument("--label", default=None, help="training label of the env (task-indexed multi-task policies)")
    e.add_argument("--record", default=None, metavar="FILE.mcap", help="write every step to this MCAP bag")
    e.add_argument(
        "--record-every", type=int, default=None, metavar="N", help="with --record: a new file every N episodes"
    )
    e.add_argument(
        "--placement",
        choices=("inprocess", "workers"),
        default="inprocess",
        help="the env in this process (default) or in a worker process",
    )
    e.add_argument("--json", dest="json_path", default=None, metavar="PATH", help="also write the result as JSON")
    e.add_argument(
        "--sweep",
        action="store_true",
        help="success against imperfection strength (training/sweep.py), each knob alone and all together",
    )
    e.add_argument("--sweep-knobs", nargs="+", default=None, metavar="KNOB", help="with --sweep: these curves only")
    e.add_argument("--strengths", nargs="+", type=float, default=None, help="with --sweep: these strengths only")
    e.add_argument("--plot", default=None, metavar="PNG", help="with --sweep: plot success against strength")
    e.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = subparsers.add_parser("plot", help="learning curves (episode length, return, success rate) to PNG")
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories of `uniros train`")
    p.add_argument("--out", default=None, help="PNG path (default RUN_DIR/curves.png)")
    p.add_argument("--labels", nargs="+", default=None, help="one legend label per run")
    p.add_argument("--window", type=int, default=20, help="episodes per moving average (default 20)")
    p.add_argument("--title", default=None, help="figure title")
    p.add_argument("--tasks", nargs="+", default=None, help="draw only these envs of each run (e.g. ned2_sim)")
    p.add_argument(
        "--x",
        choices=("steps", "minutes"),
        default="steps",
        help="x axis: env steps (default) or wall-clock minutes since training started (real-time runs)",
    )


def _yaml_value(text: str, what: str) -> Any:
    try:
        return loads_yaml(text)  # as in config files: 3e-4 and 1e4 are numbers
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what}: not valid YAML: {text!r}") from exc


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = _yaml_value(value, f"--set {key}")
    if args.name is not None:
        out["name"] = args.name
    if args.steps is not None:
        out["total_steps"] = args.steps
    if args.seed is not None:
        out["seed"] = args.seed
    if args.learner is not None:
        out["learner"] = args.learner
    if args.run_dir is not None:
        out["run_dir"] = args.run_dir
    if args.env:
        kw = _yaml_value(args.env_kwargs, "--env-kwargs") if args.env_kwargs else {}
        if not isinstance(kw, dict):
            raise ConfigError(f"--env-kwargs must be a mapping, got {args.env_kwargs!r}")
        out["envs"] = [{"id": env_id, "kwargs": kw} for env_id in args.env]
    elif args.env_kwargs:
        raise ConfigError("--env-kwargs needs --env")
    return out


def _run_train(args: argparse.Namespace) -> int:
    from uniros_async.training.config import load_train_config, train_config_from_dict
    from uniros_async.training.recipes import TrainingInterrupted, train

    overrides = _overrides(args)
    if args.config is not None:
        cfg = load_train_config(args.config, overrides)
    elif args.resume and args.run_dir:
        stored = Path(args.run_dir) / "config.yaml"
        if not stored.is_file():
            raise ConfigError(f"--resume without CONFIG reads {stored}, which does not exist")
        cfg = load_train_config(stored, overrides)
    elif args.env:
        from uniros_async.training.config import apply_overrides

        cfg = train_config_from_dict(apply_overrides({}, overrides), where="command line")
    else:
        raise ConfigError("uniros train needs CONFIG.yaml, --env ID, or --resume --run-dir DIR")
    print(
        f"training {cfg.name}: {cfg.total_steps} steps on {', '.join(cfg.labels())}, learner {cfg.learner}, "
        f"run dir {cfg.resolved_run_dir()}",
        flush=True,
    )
    try:
        result = train(cfg, resume=args.resume, progress=False if args.no_progress else None)
    except TrainingInterrupted as exc:
        print(f"uniros: {exc}", file=sys.stderr)
        return 130
    print(f"done: {result.steps} steps in {result.wall_time_s / 60:.1f} min; checkpoint {result.checkpoint}")
    for r in result.final_eval:
        print("  " + r.summary())
    return 0


def _run_eval(args: argparse.Namespace) -> int:
    from uniros_async.training.config import EnvEntry
    from uniros_async.training.evaluate import evaluate_checkpoint

    if args.env_kwargs is not None:
        kwargs = _yaml_value(args.env_kwargs, "--env-kwargs") if args.env_kwargs else {}
        if not isinstance(kwargs, dict):
            raise ConfigError(f"--env-kwargs must be a mapping, got {args.env_kwargs!r}")
    else:  # as the policy was trained on this env (its action mode, reward, robot): anything else is a new task
        from uniros_async.training.checkpoint import find_checkpoint, read_meta
        from uniros_async.training.evaluate import training_kwargs

        trained = training_kwargs(read_meta(find_checkpoint(args.checkpoint)), args.env, args.label)
        kwargs = dict(trained or {})
        if kwargs:
            print(f"env kwargs as in training: {kwargs} (--env-kwargs to choose others)")
    kwargs.setdefault("clock", args.clock)
    if args.robot is not None:
        kwargs["robot"] = args.robot
    if args.episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {args.episodes}")
    label = args.label or EnvEntry(id=args.env, kwargs=kwargs).label()
    if args.sweep:
        return _run_sweep(args, kwargs, label)
    bar: Any = None
    wins = [0]

    def on_episode(i: int, ok: bool, ret: float, length: int) -> None:
        nonlocal bar
        wins[0] += ok
        if bar is None and not args.no_progress:  # created here: errors found before the first episode print alone
            from uniros_async._progress import progress_bar

            bar = progress_bar(total=args.episodes, unit="ep", desc=label, mininterval=1.0)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"success {100 * wins[0] / (i + 1):.1f}%", refresh=False)

    try:
        result = evaluate_checkpoint(
            args.checkpoint,
            args.env,
            kwargs,
            episodes=args.episodes,
            seed=args.seed,
            label=label,
            placement=args.placement,
            on_episode=on_episode,
            record=args.record,
            record_episodes_per_file=args.record_every,
        )
    finally:
        if bar is not None:
            bar.close()
    print(f"{result.env_id} {kwargs}, {result.episodes} episodes, seed {args.seed}")
    print(f"success rate: {100 * result.success_rate:.1f} % ({result.successes}/{result.episodes})")
    print(f"mean return: {result.mean_return:.3f} (std {result.std_return:.3f})")
    print(f"mean episode length: {result.mean_length:.2f}")
    if args.record:
        every = f" (a file every {args.record_every} episodes)" if args.record_every else ""
        print(f"steps recorded to {args.record}{every}")
    if result.normalized_obs:
        print("observations: normalised with the checkpoint's statistics (trained with normalize_obs)")
    else:
        print("observations: as the env gives them (trained without normalize_obs)")
    if args.json_path:
        Path(args.json_path).write_text(json.dumps({**result.to_dict(), "checkpoint": str(args.checkpoint)}, indent=2))
    return 0


def _run_sweep(args: argparse.Namespace, kwargs: dict[str, Any], label: str) -> int:
    from uniros_async.training.sweep import CURVES, STRENGTHS, plot_sweep, sweep_checkpoint, write_sweep

    def on_point(curve: str, strength: float, point: dict[str, Any]) -> None:
        print(
            f"{curve} {strength:g}: success {100 * point['success_rate']:.1f} % ({point['successes']}/"
            f"{point['episodes']}), mean length {point['mean_length']:.2f}",
            flush=True,
        )

    result = sweep_checkpoint(
        args.checkpoint,
        args.env,
        kwargs,
        episodes=args.episodes,
        seed=args.seed,
        curves=args.sweep_knobs or CURVES,
        strengths=args.strengths or STRENGTHS,
        label=args.label,
        on_point=on_point,
    )
    if args.json_path:
        print(f"wrote {write_sweep(result, args.json_path)}")
    if args.plot:
        print(f"wrote {plot_sweep([result], args.plot)}")
    return 0


def _run_plot(args: argparse.Namespace) -> int:
    from uniros_async.training.plot import plot_runs

    out = plot_runs(
        args.run_dirs,
        out=args.out,
        labels=args.labels,
        window=args.window,
        title=args.title,
        x=args.x,
        tasks=args.tasks,
    )
    print(f"wrote {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """Run a parsed ``uniros train|eval|plot``; returns the exit code (UnirosError is reported by the caller)."""
    if args.command == "train":
        return _run_train(args)
    if args.command == "eval":
        return _run_eval(args)
    return _run_plot(args)
