"""The evaluation of ``eval.alongside``: a second set of a concurrent run's envs, evaluated on a thread of its own
with a frozen copy of the policy while training goes on, so that the arms that train never stand still for an
evaluation."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from uniros_async.errors import UnirosError
from uniros_async.priority import real_time_thread
from uniros_async.training.evaluate import EvalResult, evaluate_vec_policy, frozen_obs_stats

if TYPE_CHECKING:
    from uniros_async.training.concurrent import ConcurrentVecEnv

__all__ = ["JOIN_S", "Alongside", "FrozenPolicy"]

# how long closing waits for the evaluation thread of eval.alongside: it checks its stop event before every step,
# and a step waits at most for its action cycle or the workers' step deadline
JOIN_S = 60.0


class FrozenPolicy:
    """A copy of a model's policy (and observation statistics) at one step, for an evaluation on another thread:
    the learner goes on updating the model's networks while it acts."""

    def __init__(self, model: Any) -> None:
        import copy

        paused = getattr(model, "learner_paused", contextlib.nullcontext)
        with paused():  # AsyncTD3: between two updates, so the copy is one consistent set of weights
            self.policy = copy.deepcopy(model.policy)
        self.policy.set_training_mode(False)
        live = model.get_vec_normalize_env()
        self.stats = None if live is None else frozen_obs_stats(live)

    def predict(self, observation: Any, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The copied policy's actions (SB3's ``predict``)."""
        actions, _ = self.policy.predict(observation, deterministic=deterministic)
        return actions, None

    def get_vec_normalize_env(self) -> Any:
        """The observation statistics at the copy's step (frozen), or None."""
        return self.stats


class Alongside:
    """The periodic evaluation of ``eval.alongside``: a second ConcurrentVecEnv of the training envs, stepped by a
    thread of its own (one evaluation at a time) while training goes on. ``request`` starts an evaluation with a
    copy of the policy (or, while one runs, marks the next as due), ``take`` hands over a finished one's results,
    ``close`` stops a running one (within one action cycle) and closes the envs.

    With ``real_time`` (envs on the wall clock, as the acting thread of training has it) the thread that steps the
    evaluation envs runs in the real-time class for the evaluation (``priority.real_time_thread``, at the acting
    thread's priority, above every env loop): without it a learner, torch or the training thread delays the
    evaluation's actions by scheduler slices, and its arms' action cycles spread. ``real_time_class`` says whether
    the last evaluation's thread had the class (it may not be permitted)."""

    def __init__(self, venv: ConcurrentVecEnv, env_ids: list[str], *, real_time: bool = False) -> None:
        self.venv = venv
        self.env_ids = env_ids
        self.real_time = real_time
        self.real_time_class = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._outcome: tuple[int, float, list[EvalResult] | BaseException] | None = None
        self._due = False  # an evaluation fell due while another ran

    def busy(self) -> bool:
        """Whether an evaluation runs (or has ended and waits for ``take``)."""
        return self._thread is not None

    def request(self, model: Any, step: int, episodes: int, seed: int) -> None:
        """Evaluate the policy as it is at ``step``, now or (one running) when the running one ends."""
        if self.busy():
            self._due = True
            return
        policy = FrozenPolicy(model)
        t0 = time.monotonic()

        def run() -> None:
            try:
                out: list[EvalResult] | BaseException = self.evaluate(policy, episodes, seed, self._stop)
            except BaseException as exc:  # noqa: BLE001 - handed to the training thread by take()
                out = exc
            self._outcome = (step, time.monotonic() - t0, out)

        self._thread = threading.Thread(target=run, name=f"eval-alongside-{step}", daemon=True)
        self._thread.start()

    def evaluate(self, policy: Any, episodes: int, seed: int, stop: threading.Event | None = None) -> list[EvalResult]:
        """One evaluation of ``policy`` on the envs (in the calling thread, in the real-time class with
        ``real_time``), their action-cycle timing kept."""
        with real_time_thread() if self.real_time else contextlib.nullcontext(False) as rt:
            self.real_time_class = rt
            results = evaluate_vec_policy(
                policy, self.venv, episodes, self.venv.labels, seed=seed, env_ids=self.env_ids, stop=stop
            )
        self.venv.timing_window()  # the evaluation's action cycles, kept in venv.samples for timing.json
        return results

    def take(self, model: Any, step: int, episodes: int, seed: int) -> tuple[int, float, list[EvalResult]] | None:
        """A finished evaluation's (step, seconds it took, results), or None; starts the one that fell due meanwhile
        (with the policy at ``step``). Raises what the evaluation raised (e.g. WorkerError)."""
        thread = self._thread
        if thread is None or thread.is_alive():
            return None
        thread.join()
        self._thread = None
        assert self._outcome is not None
        done_step, took_s, out = self._outcome
        self._outcome = None
        if isinstance(out, BaseException):
            raise out
        if self._due:
            self._due = False
            self.request(model, step, episodes, seed)
        return done_step, took_s, out

    def cancel(self) -> None:
        """Stop a running evaluation (it ends before its next step, within an action cycle) and drop it."""
        self._due = False
        thread = self._thread
        if thread is not None:
            self._stop.set()
            thread.join(JOIN_S)
            if thread.is_alive():
                raise UnirosError(f"the evaluation alongside training did not stop within {JOIN_S:.0f} s")
            self._thread = None
            self._outcome = None
            self._stop.clear()

    def close(self) -> None:
        """``cancel`` and close the envs."""
        try:
            self.cancel()
        finally:
            self.venv.close()
