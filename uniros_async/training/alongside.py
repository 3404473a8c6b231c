"""The evaluation of ``eval.alongside``: a second set of a concurrent run's envs, evaluated in a process of its own
(eval_process.py) with a copy of the policy taken at the evaluation's step, while training goes on, so that the arms
that train never stand still for an evaluation and no learner update delays an evaluation arm's action."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Sequence
from typing import Any

from uniros_async.errors import ConfigError, UnirosError
from uniros_async.training.concurrent import TIMING_METRICS
from uniros_async.training.eval_process import EvalProcess, EvalReply, EvalRequest, open_eval_process
from uniros_async.training.evaluate import EvalResult, frozen_obs_stats

__all__ = ["RANKS", "Alongside", "open_alongside", "phase_bases", "phased", "policy_request", "rank_bases"]

RANKS = ("training", "evaluation")
"""The values of ``eval.alongside_rank``: which set of arms' env loops ranks higher in the real-time class."""


def policy_request(model: Any, episodes: int, seed: int, *, with_skeleton: bool) -> EvalRequest:
    """An evaluation request with ``model``'s policy as it is now: the weights of its actor (of the policy if it has
    none) as numpy arrays, copied between two updates of an ``AsyncTD3`` learner (``learner_paused``), and the
    observation statistics frozen at the same step; with ``with_skeleton``, also the policy's class and constructor
    arguments (SB3's own ``BasePolicy.save`` keeps the same two)."""
    policy = model.policy
    module = getattr(policy, "actor", policy)
    paused = getattr(model, "learner_paused", contextlib.nullcontext)
    with paused():  # one consistent set of weights
        weights = {k: v.detach().cpu().numpy().copy() for k, v in module.state_dict().items()}
    live = model.get_vec_normalize_env()
    skeleton = (type(policy), policy._get_constructor_parameters()) if with_skeleton else None
    return EvalRequest(
        weights=weights,
        skeleton=skeleton,
        obs_stats=None if live is None else frozen_obs_stats(live),
        episodes=episodes,
        seed=seed,
    )


class Alongside:
    """The periodic evaluation of ``eval.alongside`` over an evaluation process (one evaluation at a time).
    ``request`` starts an evaluation with the policy as it is (or, while one runs, marks the next as due), ``take``
    hands over a finished one's results, ``cancel`` stops a running one (within one action cycle), ``evaluate``
    runs one to its end (the final evaluation), ``close`` stops the process and its envs.

    With ``real_time`` (envs on the wall clock, as the acting thread of training has it) the process evaluates in
    the real-time class (``priority.real_time_thread``, at the acting thread's priority, above every env loop);
    ``real_time_class`` says whether the last evaluation had it (it may not be permitted). ``samples`` holds every
    evaluation's action-cycle timing per env label and metric (ms), as ``ConcurrentVecEnv.samples`` does.
    """

    def __init__(self, process: EvalProcess) -> None:
        self.process = process
        self.labels = list(process.labels)
        self.real_time_class = False
        self.samples: dict[str, dict[str, list[float]]] = {lab: {m: [] for m in TIMING_METRICS} for lab in self.labels}
        self._rid: int | None = None
        self._step = 0
        self._t0 = 0.0
        self._policy_sent: Any = None  # the policy whose skeleton the process holds
        self._due = False  # an evaluation fell due while another ran

    def busy(self) -> bool:
        """Whether an evaluation runs (or has ended and waits for ``take``)."""
        return self._rid is not None

    def request(self, model: Any, step: int, episodes: int, seed: int) -> None:
        """Evaluate the policy as it is at ``step``, now or (one running) when the running one ends.

        Raises:
            UnirosError: the evaluation process has exited.
        """
        if self.busy():
            self._due = True
            return
        self._rid = self._submit(model, episodes, seed)
        self._step, self._t0 = step, time.monotonic()

    def take(self, model: Any, step: int, episodes: int, seed: int) -> tuple[int, float, list[EvalResult]] | None:
        """A finished evaluation's (step, seconds it took, results), or None; starts the one that fell due meanwhile
        (with the policy at ``step``).

        Raises:
            WorkerError: an evaluation env's worker failed (what the evaluation raised, raised again here).
            UnirosError: the evaluation process exited, or made no progress for ``eval_process.STALL_S``.
        """
        if self._rid is None:
            return None
        reply = self.process.poll(self._rid)
        if reply is None:
            return None
        self._rid = None
        results = self._results(reply)
        done = (self._step, time.monotonic() - self._t0, results)
        if self._due:
            self._due = False
            self.request(model, step, episodes, seed)
        return done

    def evaluate(self, model: Any, episodes: int, seed: int) -> list[EvalResult]:
        """One evaluation of ``model``'s policy as it is, to its end (``cancel`` a running one first).

        Raises:
            UnirosError: one runs already; or as ``take``.
        """
        if self.busy():
            raise UnirosError("an evaluation alongside training is still running: cancel it first")
        rid = self._submit(model, episodes, seed)
        return self._results(self.process.wait(rid))

    def cancel(self) -> None:
        """Stop a running evaluation (it ends before its next step, within an action cycle) and drop it."""
        self._due = False
        rid, self._rid = self._rid, None
        if rid is not None:
            self.process.stop(rid)

    def close(self) -> None:
        """``cancel`` and close the evaluation process (its envs with it)."""
        try:
            self.cancel()
        finally:
            self.process.close()

    def _submit(self, model: Any, episodes: int, seed: int) -> int:
        fresh = model.policy is not self._policy_sent
        rid = self.process.submit(policy_request(model, episodes, seed, with_skeleton=fresh))
        self._policy_sent = model.policy
        return rid

    def _results(self, reply: EvalReply) -> list[EvalResult]:
        if reply.error is not None:
            raise reply.error
        if reply.stopped:
            raise UnirosError("the evaluation alongside training was stopped")
        self.real_time_class = reply.real_time
        for label, metrics in reply.window.items():
            for metric, samples in metrics.items():
                self.samples[label][metric].extend(samples)
        return list(reply.results)


def rank_bases(rank: str, n_envs: int) -> tuple[int, int]:
    """The lowest real-time ranks (``make_vec``'s ``rt_rank_base``) of the training envs' loops and of the
    evaluation envs' loops, ``n_envs`` of each, with ``rank`` (``eval.alongside_rank``) the set that ranks higher.

    Raises:
        ConfigError: ``rank`` is not one of ``RANKS``, or ``n_envs`` is below 1.
    """
    if rank not in RANKS:
        raise ConfigError(f"eval.alongside_rank must be one of {', '.join(RANKS)}, got {rank!r}")
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise ConfigError(f"the number of envs must be an int >= 1, got {n_envs!r}")
    return (n_envs, 0) if rank == "training" else (0, n_envs)


def phase_bases(rank: str, n_envs: int) -> tuple[int, int]:
    """The lowest loop phases (``make_vec``'s ``loop_phase_base``, in ``worker.LOOP_PHASE_STEP_NS``) of the training
    envs' loops and of the evaluation envs' loops, ``n_envs`` of each: the set that ranks higher (``rank``) ticks
    first, the other after it.

    Every loop ticks once a period, also in the action cycles in which its set does not step, so the two sets'
    ticks meet in every period, whatever ``eval.alongside_phase``. A set's step hands out its actions just after its
    own loops' ticks: ticking first, the higher set's actions reach their loops while the lower set ticks, and take
    the cores from those loops; ticking after, the lower set's actions arrive when the higher set's ticks are done,
    where with the phases the other way round they would wait behind the higher set's ticks.

    Raises:
        ConfigError: as ``rank_bases``.
    """
    training, evaluation = rank_bases(rank, n_envs)
    return evaluation, training


def phased(specs: Sequence[tuple[str, str, dict[str, Any]]], phase: float) -> list[tuple[str, str, dict[str, Any]]]:
    """``specs`` ((label, id, kwargs)) with each env's ``action_cycle_phase`` moved on by ``phase`` (mod 1).

    Raises:
        ConfigError: ``phase`` is outside [0, 1).
    """
    if isinstance(phase, bool) or not isinstance(phase, (int, float)) or not 0 <= phase < 1:
        raise ConfigError(f"eval.alongside_phase must be a number in [0, 1), got {phase!r}")
    return [
        (label, env_id, {**kw, "action_cycle_phase": (float(kw.get("action_cycle_phase", 0.0)) + phase) % 1.0})
        for label, env_id, kw in specs
    ]


def open_alongside(
    specs: Sequence[tuple[str, str, dict[str, Any]]],
    *,
    real_time: bool,
    torch_threads: int = 1,
    rank: str = "training",
    phase: float = 0.5,
    task_id: bool = False,
) -> Alongside:
    """The evaluation of ``eval.alongside`` on a second set of the envs ``specs`` ((label, id, kwargs), the run's
    training envs), in an evaluation process of its own that is ready when this returns; the envs' loops rank below
    the training envs' with ``rank`` "training" (the training envs opened with ``rank_bases``' training base),
    above them with "evaluation" (``make_vec``'s ``rt_rank_base``), and tick after the higher set's loops
    (``phase_bases``); on a wall clock their action cycles fall
    ``phase`` of a cycle after the training envs' (``action_cycle_phase``, ``eval.alongside_phase``); ``task_id`` as
    the training envs' (``task_id_in_obs``).

    Raises:
        ConfigError: ``rank`` is not one of ``RANKS``, or ``phase`` is outside [0, 1).
        ConfigError, WorkerError: the envs could not be opened.
        UnirosError: the evaluation process did not start.
    """
    base, phase_base = rank_bases(rank, len(specs))[1], phase_bases(rank, len(specs))[1]
    if real_time:
        specs = phased(specs, phase)
    process = open_eval_process(
        specs,
        real_time=real_time,
        torch_threads=torch_threads,
        rt_rank_base=base,
        loop_phase_base=phase_base,
        task_id=task_id,
    )
    return Alongside(process)
