"""make_vec(): heterogeneous envs padded, parallel steps, NEXT_STEP autoreset, goal envs, and SB3 on top."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest
from _children import children

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import UnirosVectorEnv, make_vec

pytestmark = pytest.mark.slow

RX, NED = "uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"


def test_mixed_rx200_ned2_are_padded_and_say_so_in_infos() -> None:
    venv = make_vec([RX, (NED, {"reward_type": "sparse"})], clock="sim")
    try:
        assert isinstance(venv, UnirosVectorEnv) and isinstance(venv, gym.vector.VectorEnv)
        assert venv.num_envs == 2
        assert venv.single_observation_space.shape == (28,)  # rx200 28, ned2 25
        assert venv.single_action_space.shape == (6,)  # rx200 5, ned2 6
        assert venv.observation_space.shape == (2, 28) and venv.action_space.shape == (2, 6)
        obs, info = venv.reset(seed=0)
        assert obs.shape == (2, 28) and obs.dtype == np.float32
        assert obs[1, -1] == 0.0  # ned2's padding
        assert list(info["env_id"]) == [RX, NED]
        assert list(info["padding"]["observation"]) == [0, 3]
        assert list(info["padding"]["action"]) == [1, 0]
        venv.action_space.seed(0)
        ended = np.zeros(2, dtype=bool)
        for _ in range(5):
            obs, rewards, terminated, truncated, info = venv.step(venv.action_space.sample())
            assert obs.shape == (2, 28) and rewards.shape == (2,) and terminated.dtype == np.bool_
            assert obs[1, -1] == 0.0
            # the sparse reward reached the ned2 worker; a random action may reach the goal and end the episode,
            # and then the next step is gymnasium's NEXT_STEP autoreset, which resets and returns 0.0
            assert rewards[1] == 0.0 if ended[1] else rewards[1] in (-1.0, 1.0), (rewards, ended)
            ended = terminated | truncated
            assert list(info["env_id"]) == [RX, NED]
        # every local member got the same reference instant with its step, the one a wall-clock env decides a new
        # deadline from (a sim-clock env never reads it, so it is still there to see)
        t0 = time.monotonic_ns()
        venv.step(venv.action_space.sample())
        refs = venv.get_attr("step_reference_ns")
        assert refs[0] == refs[1] and isinstance(refs[0], int) and t0 <= refs[0] <= time.monotonic_ns()
        # step_async / step_wait are plain methods
        venv.step_async(np.zeros((2, 6), np.float32))
        obs, *_ = venv.step_wait()
        assert obs.shape == (2, 28)
        with pytest.raises(gym.error.InvalidAction):
            venv.step(np.zeros((2, 5), np.float32))
    finally:
        venv.close()
        venv.close()
    assert children() == []


def test_step_async_sends_without_running_the_loop_and_falls_back_when_it_cannot(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """step_async writes every request into the workers' shm rings from the caller's thread, and step_wait and step
    take the replies there too (the supervisor's loop never runs); with a ring that refuses (try_send False) the
    loop path sends and receives, with the same results."""
    from uniros_async.transports import shm

    def run(venv: UnirosVectorEnv, fast: bool) -> list[np.ndarray]:
        venv.reset(seed=0)
        rng = np.random.default_rng(3)
        out = []
        drives = []
        sup = venv._sup
        real_drive = sup._drive
        monkeypatch.setattr(sup, "_drive", lambda *a, **k: drives.append(1) or real_drive(*a, **k))
        for _ in range(4):
            drives.clear()
            venv.step_async(rng.uniform(-1, 1, (2, 6)).astype(np.float32))
            pending = venv._pending
            assert pending is not None
            workers = sup.workers
            assert len(drives) == (0 if fast else 1)  # fast: sent from this thread, the loop did not run
            if fast:  # (the loop path may already have taken a quick reply)
                assert all(w.in_flight for w in workers)
                deadline = time.monotonic() + 10.0  # accelerated workers answer on their own
                while time.monotonic() < deadline and not all(
                    w.transport._rx_ctl[shm.W_POS] != w.transport._ring.rpos for w in workers
                ):
                    time.sleep(0.01)
                assert all(w.transport._rx_ctl[shm.W_POS] != w.transport._ring.rpos for w in workers), "replies due"
            # the loop path: step_wait runs the loop once more, unless the loop already took the replies while it
            # sent (accelerated workers on a fast machine answer within that drive); the fast path never runs it
            out.append(venv.step_wait()[0])
            assert len(drives) in ((0,) if fast else (1, 2))
            before = len(drives)
            out.append(venv.step(rng.uniform(-1, 1, (2, 6)).astype(np.float32))[0])
            assert len(drives) - before in ((0,) if fast else (1, 2))
        return out

    specs = [(RX, {"turn_based": True}), (NED, {"turn_based": True})]
    venv = make_vec(specs, clock="sim")
    try:
        from uniros_async.runtime.supervisor import REPLY_SPIN_NS

        assert all(not w.info["realtime"] and w.transport.spin_ns == REPLY_SPIN_NS for w in venv._sup.workers)
        fast = run(venv, True)
    finally:
        venv.close()
    monkeypatch.setattr(shm.ShmTransport, "try_send", lambda self, frame: False)
    venv = make_vec(specs, clock="sim")
    try:
        slow = run(venv, False)
    finally:
        venv.close()
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_array_equal(a, b)


def test_next_step_autoreset_after_truncation() -> None:
    venv = make_vec([(RX, {"max_episode_steps": 3})], clock="sim")
    try:
        venv.reset(seed=0)
        a = np.zeros((1, 5), np.float32)
        for _ in range(2):
            _, _, terminated, truncated, _ = venv.step(a)
            assert not truncated[0]
        _, _, terminated, truncated, _ = venv.step(a)
        assert truncated[0] or terminated[0]
        _, rewards, terminated, truncated, _ = venv.step(a)  # the reset step
        assert rewards[0] == 0.0 and not terminated[0] and not truncated[0]
    finally:
        venv.close()


def test_goal_envs_pad_the_observation_key() -> None:
    venv = make_vec(["uniros/Rx200ReachGoal-v0", "uniros/Ned2ReachGoal-v0"], clock="sim")
    try:
        space = venv.single_observation_space
        assert isinstance(space, gym.spaces.Dict)
        # rx200 24, ned2 21: the standard vector without the direction to the goal and distance
        # (HER relabels desired_goal only)
        assert space["observation"].shape == (24,) and space["desired_goal"].shape == (3,)
        obs, info = venv.reset(seed=2)
        assert obs["observation"].shape == (2, 24) and obs["achieved_goal"].shape == (2, 3)
        obs, *_ = venv.step(venv.action_space.sample())
        assert obs["observation"][1, -1] == 0.0
    finally:
        venv.close()


def test_spaces_that_cannot_be_combined_name_the_envs() -> None:
    with pytest.raises(ConfigError, match="Rx200ReachGoal-v0") as e:
        make_vec([RX, "uniros/Rx200ReachGoal-v0"], clock="sim")
    assert RX in str(e.value)
    with pytest.raises(ConfigError, match="cannot be combined"):
        make_vec([RX, NED], clock="sim", pad=False)
    assert children() == []


def test_bad_spec_fails_before_any_process() -> None:
    with pytest.raises(ConfigError, match="spec 1"):
        make_vec([RX, 42])  # type: ignore[list-item]
    with pytest.raises(ConfigError, match="registered uniros ids"):
        make_vec([RX, "uniros/Nope-v0"])
    assert children() == []


def test_sb3_td3_trains_on_mixed_rx200_ned2() -> None:
    import torch
    from stable_baselines3 import TD3
    from stable_baselines3.common.vec_env import VecEnv

    torch.set_num_threads(1)
    venv = make_vec([RX, NED], clock="sim")
    try:
        sb3_env = venv.as_sb3()
        assert isinstance(sb3_env, VecEnv)
        assert sb3_env.num_envs == 2 and sb3_env.observation_space.shape == (28,)
        model = TD3(
            "MlpPolicy",
            sb3_env,
            learning_starts=50,
            train_freq=(4, "step"),
            gradient_steps=1,
            batch_size=32,
            policy_kwargs={"net_arch": [32, 32]},
            seed=0,
            device="cpu",
            verbose=0,
        )
        model.learn(total_timesteps=200)
        assert model.num_timesteps >= 200
        action, _ = model.predict(sb3_env.reset(), deterministic=True)
        assert action.shape == (2, 6)
    finally:
        venv.close()


def test_a_worker_that_cannot_start_is_named_and_the_others_are_closed() -> None:
    with pytest.raises(WorkerError) as e:
        make_vec([RX, (NED, {"goal_min": [0.3, 0.0, 0.2]})], clock="sim")  # above the arm's default goal_max
    assert e.value.index == 1 and NED in str(e.value) and "goal_min/goal_max" in str(e.value)
    assert "ConfigError" in e.value.remote_traceback
    assert children() == []


@pytest.mark.serial  # real-time loops held to their tick phases
@pytest.mark.parametrize(("rt_rank_base", "loop_phase_base"), [(0, None), (2, 0)])
def test_real_time_mixed_placements(rt_rank_base: int, loop_phase_base: int | None) -> None:
    """Wall clock, every env at its own rates: ned2 servo sim in its own process, rx200 emulated real arm (tcp).
    Asserted on the schedules the code sets, whatever the host's load: each loop ticks on its period's grid at its
    phase (by default its rank; from ``loop_phase_base`` up in rank order when given), and the members' steps return
    at the same points of the action-cycle grid (stepped together, not one after the other). How late the host runs
    them is the benchmarks'."""
    from uniros_async.envs.robot import TICK_ALIGN_NS, TICK_OFFSET_NS
    from uniros_async.runtime.worker import LOOP_PHASE_STEP_NS
    from uniros_async.transports.shm import ShmTransport

    cycle_ns = 200_000_000
    venv = make_vec(
        [(NED, {"robot": "sim-process"}), (RX, {"robot": "emulated-real"})],
        clock="wall",
        action_cycle_s=cycle_ns / 1e9,
        rt_rank_base=rt_rank_base,
        loop_phase_base=loop_phase_base,
    )
    try:
        venv.reset(seed=0)
        t0 = time.monotonic()
        for _ in range(8):
            obs, rewards, *_ = venv.step(np.zeros((2, 6), np.float32))
        elapsed = time.monotonic() - t0
        assert obs.shape == (2, 28) and np.all(np.isfinite(rewards))
        assert elapsed > 7 * cycle_ns / 1e9, elapsed  # eight steps end on eight successive points of the grid
        # real-time workers: the agent keeps the transport's short reply poll (supervisor.REPLY_SPIN_NS)
        for w in venv._sup.workers:
            assert w.info["realtime"] is True and w.transport.spin_ns == ShmTransport.spin_ns
        snaps = venv.call("timing_snapshot")
    finally:
        venv.close()
    assert children() == []
    # each member's loop ticks at its phase (worker.LOOP_PHASE_STEP_NS): the first worker (the higher rank) 1 ms
    # later than the second, so they do not tick at one instant; every scheduled tick, not only the punctual ones
    base = rt_rank_base if loop_phase_base is None else loop_phase_base
    steps = []
    for snap, period, rank in zip(snaps, (40_000_000, 100_000_000), (1, 0), strict=True):
        phase = (base + rank) * LOOP_PHASE_STEP_NS
        ticks = snap["tick_deadline_ns"]
        assert len(ticks) >= 1.4e9 / period and len(ticks) == len(snap["tick_ns"]), (rank, len(ticks))
        assert {t % period for t in ticks} == {TICK_OFFSET_NS + phase}, (rank, {t % period for t in ticks})
        assert all(f >= d for f, d in zip(snap["tick_ns"], ticks, strict=True)), "a tick is never early"
        steps.append([d - phase for d in snap["step_deadline_ns"]])
    # the members return together: the same points of the action-cycle grid (a step the host delayed past its
    # point moves on to a later one, for both)
    assert steps[0] == steps[1] and len(steps[0]) == 8, steps
    assert all(d % cycle_ns == (TICK_OFFSET_NS + TICK_ALIGN_NS) % cycle_ns for d in steps[0]), steps[0]
    assert np.all(np.diff(steps[0]) > 0), steps[0]


def test_sb3_her_uses_compute_reward_in_the_workers() -> None:
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer

    torch.set_num_threads(1)
    venv = make_vec(["uniros/Rx200ReachGoal-v0", "uniros/Ned2ReachGoal-v0"], clock="sim")
    try:
        sb3_env = venv.as_sb3()
        rewards = sb3_env.env_method("compute_reward", np.zeros((4, 3)), np.ones((4, 3)), [{}] * 4, indices=[1])
        assert rewards[0].shape == (4,)
        model = SAC(
            "MultiInputPolicy",
            sb3_env,
            replay_buffer_class=HerReplayBuffer,
            replay_buffer_kwargs={"n_sampled_goal": 2, "goal_selection_strategy": "future"},
            learning_starts=210,  # HER samples only after a first episode (100 steps per env) has ended
            train_freq=(4, "step"),
            batch_size=32,
            policy_kwargs={"net_arch": [32, 32]},
            seed=0,
            device="cpu",
            verbose=0,
        )
        model.learn(total_timesteps=300)
        assert model.num_timesteps >= 300
    finally:
        venv.close()


def test_a_step_stopped_half_way_is_finished_by_the_event_loop_with_the_same_returns(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A step sent and collected in the caller's thread (``try_send`` / ``receive_blocking``) hands what is left to
    the event loop when a ring refuses a request after the first one went, or a reply cannot be taken in this
    thread: the returns are those of an undisturbed run (real workers, deterministic CartPole)."""
    from uniros_async.transports import shm

    def run() -> list[tuple[np.ndarray, np.ndarray]]:
        venv = make_vec(["CartPole-v1", "CartPole-v1"], pad=False)
        try:
            venv.reset(seed=5)
            out = []
            for k in range(40):
                obs, rew, term, trunc, _ = venv.step(np.array([k % 2, (k // 3) % 2]))
                out.append((obs, np.stack([rew, term, trunc])))
            return out
        finally:
            venv.close()

    clean = run()
    calls = {"send": 0, "receive": 0}
    real_try_send, real_receive = shm.ShmTransport.try_send, shm.ShmTransport.receive_blocking

    def flaky_try_send(self: shm.ShmTransport, frame: bytes) -> bool:
        calls["send"] += 1
        return calls["send"] % 4 != 2 and real_try_send(self, frame)  # now and then the second request of a step

    def flaky_receive(self: shm.ShmTransport, timeout_s: float) -> memoryview | None:
        calls["receive"] += 1
        return None if calls["receive"] % 3 == 0 else real_receive(self, timeout_s)

    monkeypatch.setattr(shm.ShmTransport, "try_send", flaky_try_send)
    monkeypatch.setattr(shm.ShmTransport, "receive_blocking", flaky_receive)
    disturbed = run()
    assert calls["send"] > 40 and calls["receive"] > 40  # both paths were taken, and stopped now and then
    for (a, b), (c, d) in zip(clean, disturbed, strict=True):
        np.testing.assert_array_equal(a, c)
        np.testing.assert_array_equal(b, d)


def test_replies_read_into_place_and_replies_that_cannot_be_give_the_same_returns(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``venv.step`` reads each Box observation from its reply straight into the vector observation; replies it
    cannot read that way (another dtype than the space's, ``step_wait``'s results) are cast and stacked as before:
    the returns are the same arrays either way."""
    from uniros_async.runtime import vector
    from uniros_async.runtime.protocol import pack_step_reply
    from uniros_async.runtime.vector import _Returns

    in_place = []
    real = vector.unpack_step_reply_into

    def spy(*args: object) -> object:
        got = real(*args)  # type: ignore[arg-type]
        in_place.append(got is not None)
        return got

    monkeypatch.setattr(vector, "unpack_step_reply_into", spy)
    venv = make_vec(["CartPole-v1", "CartPole-v1"], pad=False)
    try:
        venv.reset(seed=3)
        actions = [np.array([k % 2, (k // 2) % 2]) for k in range(30)]
        fast = [venv.step(a) for a in actions]
        assert len(in_place) == 60 and all(in_place)  # every reply of venv.step was read into place
        venv.reset(seed=3)
        slow = []
        for a in actions:
            venv.step_async(a)
            slow.append(venv.step_wait())
        for f, s in zip(fast, slow, strict=True):
            for x, y in zip(f[:4], s[:4], strict=True):
                np.testing.assert_array_equal(x, y)
                assert x.dtype == y.dtype
            assert f[4].keys() == s[4].keys()
        # an env that sends float64 for its float32 space: the general path, cast into the float32 batch
        obs64 = np.array([0.1, -0.2, 0.3, 1e-40])
        returns = _Returns(venv)
        frames = [pack_step_reply([obs64 * (i + 1), 1.0, i == 1, False, {"env_id": "x"}]) for i in range(2)]
        results = [returns.decode(i, memoryview(f)) for i, f in enumerate(frames)]
        assert all(type(r) is list for r in results)
        obs, rew, term, trunc, info = returns.finish(results)
        assert obs.dtype == np.float32 and obs.shape == (2, 4)
        np.testing.assert_array_equal(obs, np.stack([obs64, 2 * obs64]).astype(np.float32))
        assert rew.tolist() == [1.0, 1.0] and term.tolist() == [False, True] and not trunc.any()
        assert info["env_id"].tolist() == ["x", "x"]
    finally:
        venv.close()


def test_tcp_workers_step_in_the_callers_thread_with_the_returns_of_shm(monkeypatch: pytest.MonkeyPatch) -> None:
    """Workers over tcp (``transport="tcp"``) get their requests and give their replies without the supervisor's
    event loop too (``TcpTransport.try_send`` / ``receive_blocking``): same trajectory as over shm."""
    from uniros_async.transports import tcp

    taken = []
    real = tcp.TcpTransport.receive_blocking

    def spy(self: tcp.TcpTransport, timeout_s: float) -> memoryview | None:
        got = real(self, timeout_s)
        taken.append(got is not None)
        return got

    monkeypatch.setattr(tcp.TcpTransport, "receive_blocking", spy)
    runs = {}
    for transport in ("shm", "tcp"):
        venv = make_vec(["CartPole-v1", "CartPole-v1"], pad=False, transport=transport)
        try:
            venv.reset(seed=7)
            runs[transport] = [venv.step(np.array([k % 2, (k // 3) % 2]))[:4] for k in range(30)]
        finally:
            venv.close()
    assert len(taken) == 60 and all(taken)  # every reply was taken in this thread
    for a, b in zip(runs["shm"], runs["tcp"], strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_a_reply_that_cannot_be_read_raises_once_every_reply_is_in(monkeypatch: pytest.MonkeyPatch) -> None:
    """A step reply the agent cannot read (the first env's, made unreadable by a patched decoder) raises its own
    error, as ``request_all`` does, once the other workers' replies are taken too: the second worker is left with
    no reply owed, and only the first is marked broken (its replies can no longer be trusted to match its requests),
    which the next step reports by its index."""
    from uniros_async.errors import CodecError
    from uniros_async.runtime import vector

    real = vector.unpack_step_reply_into
    calls: list[int] = []

    def unreadable(frame: memoryview, out: memoryview, head: bytes) -> object:
        calls.append(1)
        if len(calls) == 1:
            raise CodecError("malformed step frame: made so by the test")
        return real(frame, out, head)

    venv = make_vec(["CartPole-v1", "CartPole-v1"], pad=False)
    try:
        venv.reset(seed=3)
        venv.step(np.array([0, 1]))
        monkeypatch.setattr(vector, "unpack_step_reply_into", unreadable)
        with pytest.raises(CodecError, match="made so by the test"):
            venv.step(np.array([1, 1]))
        assert len(calls) == 2  # the second reply was read too
        first, second = venv._sup.workers
        assert not second.in_flight and second.broken is None
        assert first.broken is not None and "interrupted" in first.broken
        with pytest.raises(WorkerError, match="worker 0"):
            venv.step(np.array([0, 0]))
    finally:
        venv.close()


async def test_a_tcp_worker_on_loopback_polls_for_requests_only_as_long_as_its_transport() -> None:
    """``cores.turn_spin_ns``: a worker keeps polling 200 us for its next request (``TURN_SPIN_NS``), except over
    tcp on loopback, where the woken worker often shares its agent's core and a long poll holds the agent off it;
    there it keeps the transport's 50 us. A real tcp connection on 127.0.0.1; the connection from another host is a
    stand-in (only its address is read: this machine has no second host)."""
    import types

    from uniros_async.runtime import cores
    from uniros_async.transports.base import TransportOptions, connect, listen

    lst = await listen("tcp://127.0.0.1:0", TransportOptions())
    try:
        client = await connect(lst.uri, TransportOptions())
        server = await lst.accept()
        try:
            assert cores.turn_spin_ns(server) == server.spin_ns == 50_000
            elsewhere = types.SimpleNamespace(scheme="tcp", spin_ns=50_000, sockname=("192.0.2.7", 5555))
            assert cores.turn_spin_ns(elsewhere) == cores.TURN_SPIN_NS == 200_000
        finally:
            await client.aclose()
            await server.aclose()
    finally:
        await lst.aclose()
    shm_end = types.SimpleNamespace(scheme="shm", spin_ns=50_000)
    assert cores.turn_spin_ns(shm_end) == cores.TURN_SPIN_NS  # shm sees a shared core by itself (_peer_here)


@pytest.mark.parametrize(
    "infos",
    [
        [{"env_id": "a", "n": 1, "x": 0.5}, {"env_id": "b", "flag": True}],
        [{"v": np.arange(3.0), "nested": {"k": 2, "s": "t"}}, {}, {"nested": {"k": 5}, "v": np.ones(3)}],
        [{"final_obs": np.zeros(2), "final_info": {"r": 1.0}}, {"final_obs": None}, {"r": np.float32(2)}],
    ],
)
def test_vector_infos_are_gymnasiums(infos: list[dict]) -> None:
    """``UnirosVectorEnv._add_info`` (the faster one) builds what gymnasium's ``VectorEnv._add_info`` builds."""
    venv = object.__new__(UnirosVectorEnv)  # only num_envs is needed: no workers
    venv.num_envs = len(infos)
    ours: dict = {}
    theirs: dict = {}
    for i, info in enumerate(infos):
        ours = venv._add_info(ours, info, i)
        theirs = gym.vector.VectorEnv._add_info(venv, theirs, info, i)

    def same(a: object, b: object) -> None:
        assert type(a) is type(b)
        if isinstance(a, dict):
            assert list(a) == list(b)
            for k in a:
                same(a[k], b[k])
        else:
            assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
            assert a.dtype == b.dtype and a.shape == b.shape
            for x, y in zip(a, b, strict=True):
                assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y

    same(ours, theirs)
