"""Tests of the SAIL reimplementation: run with `python -m pytest -q test_sail.py`."""

import copy
import glob
import os
import re
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import cpu_kernels
from buffers import ReplayBuffer, TeacherBuffer, mixed_batch
from demos import load_demos, save_demos
from envs import absorbing_state, add_features, evaluate_policy, get_env_state, make_env, rollout, set_env_state
from plumbing import ConfigError, load_checkpoint
from td3 import Actor, TD3, make_adam

HERE = os.path.dirname(os.path.abspath(__file__))
# the tests that train networks in this process use small ones, which one thread runs as fast as
# two, and two threads would contend with the single-threaded runs the suite starts beside them
torch.set_num_threads(1)
# the shipped demo files of each env, demos/<name>.npz, and their teachers' return bands (the -weak ones: below
# what standing still for 1000 steps earns)
SHIPPED = {"Hopper-v5": {"Hopper-v5": (1000, 1500), "Hopper-v5-weak": (600, 850)},
           "Walker2d-v5": {"Walker2d-v5": (1000, 1700), "Walker2d-v5-weak": (400, 850)},
           "HalfCheetah-v5": {"HalfCheetah-v5": (4000, 6000)},
           "Swimmer-v5": {"Swimmer-v5": (40, 120)}, "Ant-v5": {"Ant-v5": (1200, 1800), "Ant-v5-weak": (600, 850)}}


def run_script(*args, timeout=240):
    """`python SCRIPT ARGS` in this folder: a CompletedProcess with the exit code, stdout and stderr."""
    return run_scripts(args, timeout=timeout)[0]


def run_scripts(*commands, timeout=240, at_once=None):
    """run_script for each command, `at_once` of them at a time (default: all; a 2-core CI
    machine runs two single-threaded runs in the time of one).

    Each runs as a child of a fork server that has imported torch, torch._dynamo (which torch's
    optimizers import on first use), MuJoCo and the repo's modules once: a new interpreter would
    spend 2-3 CPU seconds on those imports, the bulk of a short run, and this suite runs scripts
    some 70 times. The child runs the script as `__main__` with its own argv, its stdout and
    stderr in files, and exits with the code a real `python SCRIPT` would. The tests of what the
    shell sees when sail.py gets Ctrl-C or SIGTERM, and of Ctrl-C while the libraries load, start
    real interpreters (subprocess.Popen)."""
    import tempfile
    at_once = at_once or len(commands)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(0, len(commands), at_once):
            chunk = commands[i:i + at_once]
            outputs = [(os.path.join(tmp, f"{i + j}.out"), os.path.join(tmp, f"{i + j}.err")) for j in range(len(chunk))]
            procs = [start_script(args, out, err) for args, (out, err) in zip(chunk, outputs)]
            for args, proc, (out, err) in zip(chunk, procs, outputs):
                proc.join(timeout)
                if proc.exitcode is None:
                    proc.kill()
                    raise subprocess.TimeoutExpired([sys.executable, *args], timeout)
                out, err = (open(path).read() if os.path.exists(path) else "" for path in (out, err))
                results.append(subprocess.CompletedProcess([sys.executable, *args], proc.exitcode, out, err))
    return results


def start_script(args, out_path, err_path):
    """`python ARGS` as a started child of the fork server (see run_scripts), its stdout and
    stderr written to the given files: a multiprocessing.Process, which `kill()` stops at once."""
    import multiprocessing
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["torch._dynamo", "mujoco", "sail", "gail", "bc", "test_sail"])
    # the environment of now, not the fork server's (a test may have set a variable since it started)
    proc = ctx.Process(target=_script_as_main, args=(args, out_path, err_path, dict(os.environ)))
    proc.start()
    return proc


def _script_as_main(args, out_path, err_path, environ):
    """In a child of the fork server: what `python ARGS[0] ARGS[1:]` does, run from this folder.
    A SystemExit or an exception ends the child as it would end the interpreter: its exit code,
    or a traceback and exit code 1."""
    import runpy
    os.chdir(HERE)
    os.environ.clear()
    os.environ.update(environ)
    for fd, path in ((1, out_path), (2, err_path)):
        os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
    script, *argv = args
    sys.argv = [script, *argv]
    sys.path.insert(0, os.path.dirname(os.path.abspath(script)))  # as python puts the script's folder first
    runpy.run_path(script, run_name="__main__")


class PointMass(gym.Env):
    """A 1-D point mass pushed by a force in [-1, 1]; dense reward = distance moved this step.

    Episodes last 100 steps and are only truncated. Pushing with +1 is optimal (return ~ 96);
    the poor teacher of the learning test pushes with a constant 0.2 (return ~ 19). sail.py
    builds it as `--env test_sail:PointMass-v0` (gymnasium imports this module, which registers it).
    """

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.v = 0.0, float(self.np_random.uniform(-0.1, 0.1))
        return np.array([self.x / 10, self.v]), {}

    def step(self, action):
        self.v = 0.8 * self.v + 0.2 * float(np.clip(action[0], -1, 1))
        self.x += self.v
        return np.array([self.x / 10, self.v]), self.v, False, False, {}


if "PointMass-v0" not in gym.registry:
    gym.register("PointMass-v0", entry_point=PointMass, max_episode_steps=100)


def assert_one_line_error(proc):
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines()  # leaving out MuJoCo's XML warning and tqdm's bar
             if line.strip() and "WARNING: compiler" not in line and not re.search(r"\d+/\d+ \[", line)]
    assert len(lines) == 1 and "error" in lines[0], proc.stderr


def fixed_actions(env_id, n, seed=0):
    space = gym.make(env_id).action_space
    space.seed(seed)
    return [space.sample() for _ in range(n)]


# ---------------------------------------------------------------------------------------------
# envs.py: the sparse episodic setting
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("env_id, ends_by", [("Hopper-v5", "terminated"), ("Swimmer-v5", "truncated")])
def test_sparse_reward_is_zero_then_the_exact_dense_sum(env_id, ends_by):
    actions = fixed_actions(env_id, 1000)
    dense = gym.make(env_id)
    dense.reset(seed=3)
    sparse = make_env(env_id, seed=3, time_feature=False)
    sparse.reset(seed=3)
    dense_rewards, sparse_rewards = [], []
    for action in actions:
        d_obs, d_rew, d_term, d_trunc, _ = dense.step(action)
        s_obs, s_rew, s_term, s_trunc, info = sparse.step(action)
        np.testing.assert_array_equal(d_obs, s_obs)
        assert (d_term, d_trunc) == (s_term, s_trunc)
        dense_rewards.append(d_rew)
        sparse_rewards.append(s_rew)
        if s_term or s_trunc:
            break
        assert info == {}  # no reward terms (reward_forward, x_velocity, ...) reach the learner
    assert (s_term if ends_by == "terminated" else s_trunc and not s_term)
    if ends_by == "truncated":
        assert len(sparse_rewards) == 1000
    assert all(r == 0.0 for r in sparse_rewards[:-1])
    assert sparse_rewards[-1] == pytest.approx(sum(dense_rewards), rel=1e-12)
    assert info["episode"]["r"] == sparse_rewards[-1]  # gymnasium's RecordEpisodeStatistics
    assert info["episode"]["l"] == len(sparse_rewards)
    assert set(info) == {"episode"}


def test_time_feature_counts_down_to_zero_at_the_time_limit():
    env = make_env("Swimmer-v5", seed=0, time_feature=True)
    obs, _ = env.reset()
    assert obs.dtype == np.float32 and obs.shape == (9,) and obs[-1] == 1.0
    for t in range(1, 1001):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        assert obs[-1] == pytest.approx(1 - t / 1000)
    assert truncated and not terminated and obs[-1] == 0.0


def test_absorbing_state_loops_once_and_is_not_terminal():
    env = make_env("Hopper-v5", seed=1, time_feature=False, absorbing=True)
    obs, _ = env.reset()
    assert obs.shape == (12,) and obs[-1] == 0.0
    rewards = []
    for action in fixed_actions("Hopper-v5", 1000):
        obs, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward)
        assert not terminated  # the critic bootstraps through the absorbing state
        if obs[-1] == 1.0:
            break
    np.testing.assert_array_equal(obs, absorbing_state(11))
    assert reward == 0.0 and not truncated
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())  # self-loop
    np.testing.assert_array_equal(obs, absorbing_state(11))
    assert truncated and not terminated and reward == info["episode"]["r"] != 0.0
    assert all(r == 0.0 for r in rewards)


def test_eval_length_counts_the_env_steps_not_the_absorbing_self_loop():
    """A hopper pushed hard falls; DAC's wrapper adds one self-loop step that is no step of the env."""
    lengths = [evaluate_policy(make_env("Hopper-v5", seed=3, time_feature=False, absorbing=absorbing),
                               lambda obs: np.ones(3, np.float32), 2)["eval_length"] for absorbing in (False, True)]
    assert lengths[0] < 1000 and lengths[1] == lengths[0]


@pytest.mark.parametrize("time_feature, absorbing", [(True, False), (False, True), (True, True)])
def test_features_added_to_demos_equal_the_online_wrappers(time_feature, absorbing):
    raw_env = make_env("Hopper-v5", seed=5, sparse=False, time_feature=False)
    actions = iter(fixed_actions("Hopper-v5", 1000, seed=2))
    episode = rollout(raw_env, lambda obs: next(actions))
    assert episode["terminated"]
    obs, act, next_obs, term = add_features(episode, 1000, time_feature, absorbing)

    online = make_env("Hopper-v5", seed=5, time_feature=time_feature, absorbing=absorbing)
    actions = iter(fixed_actions("Hopper-v5", 1000, seed=2))
    online_obs, _ = online.reset()  # the second reset of a seed-5 env, as in rollout above
    rows = []
    while True:
        action = next(actions, np.zeros(3, np.float32))
        online_next, _, terminated, truncated, _ = online.step(action)
        rows.append((online_obs, action, online_next, float(terminated)))
        online_obs = online_next
        if terminated or truncated:
            break
    assert len(rows) == len(obs)
    for i, (o, a, no, t) in enumerate(rows):
        np.testing.assert_allclose(obs[i], o, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(next_obs[i], no, rtol=1e-6, atol=1e-6)
        assert term[i] == t
        if not (absorbing and i == len(rows) - 1):  # the absorbing self-loop's action is free
            np.testing.assert_array_equal(act[i], a)
    assert term.dtype == obs.dtype == next_obs.dtype == np.float32
    assert term[-1] == (0.0 if absorbing else 1.0)


def test_make_env_rejects_unknown_ids_and_discrete_actions():
    with pytest.raises(ConfigError, match="unknown environment"):
        make_env("NoSuchEnv-v5", seed=0)
    with pytest.raises(ConfigError, match="Discrete"):
        make_env("CartPole-v1", seed=0)


def test_make_env_is_seeded():
    def first_steps(seed):
        env = make_env("Walker2d-v5", seed=seed)
        obs = [env.reset()[0]]
        obs += [env.step(env.action_space.sample())[0] for _ in range(5)]
        return np.array(obs)
    np.testing.assert_array_equal(first_steps(7), first_steps(7))
    assert not np.array_equal(first_steps(7), first_steps(8))


@pytest.mark.parametrize("env_id", ["Ant-v5", "Walker2d-v5"])
def test_an_env_restored_mid_episode_steps_exactly_as_the_original(env_id):
    # Ant-v5's reward reads the torso's position as MuJoCo's last substep left it: a restore that
    # recomputed it at the current state changed the first step's reward (-0.1806 against -0.1831)
    original, restored = make_env(env_id, seed=3, sparse=False), make_env(env_id, seed=4, sparse=False)
    original.reset()
    restored.reset()
    for _ in range(20):
        original.step(original.action_space.sample())
    set_env_state(restored, get_env_state(original))
    for _ in range(5):
        action = original.action_space.sample()
        assert restored.action_space.sample().tolist() == action.tolist()
        step_original, step_restored = original.step(action), restored.step(action)
        assert step_original[1] == step_restored[1]  # the reward, bit for bit
        np.testing.assert_array_equal(step_original[0], step_restored[0])


# ---------------------------------------------------------------------------------------------
# buffers.py
# ---------------------------------------------------------------------------------------------

def test_replay_buffer_is_float32_and_small_enough():
    buffer = ReplayBuffer(obs_dim=18, act_dim=6, capacity=1_000_000)  # Walker2d + time feature
    assert all(t.dtype == torch.float32 for t in buffer.tensors())
    assert sum(t.numel() * t.element_size() for t in buffer.tensors()) < 0.25e9


def test_replay_buffer_samples_only_what_was_added_and_wraps():
    buffer = ReplayBuffer(obs_dim=2, act_dim=1, capacity=10)
    for i in range(14):  # 14 > capacity: the first 4 are overwritten
        buffer.add([i, i], [i], float(i), [i + 1, i + 1], i % 2)
    assert buffer.size == 10
    torch.manual_seed(0)
    obs, actions, rewards, next_obs, terminated = buffer.sample(500)
    assert obs.shape == (500, 2) and actions.shape == (500, 1) and rewards.shape == (500,)
    assert set(obs[:, 0].tolist()) == set(range(4, 14))
    torch.testing.assert_close(next_obs, obs + 1)
    torch.testing.assert_close(terminated, obs[:, 0] % 2)
    recent, *_ = buffer.sample_recent(200, window=3)
    assert set(recent[:, 0].tolist()) == {11, 12, 13}
    restored = ReplayBuffer(obs_dim=2, act_dim=1, capacity=10)  # as the probes read R_B from a checkpoint
    restored.load_state_dict(buffer.state_dict())
    assert restored.latest(5)[0][:, 0].tolist() == [9, 10, 11, 12, 13]  # the newest steps, across the wrap


def test_episode_returns_mark_finished_episodes_only_and_wrap():
    buffer = ReplayBuffer(obs_dim=1, act_dim=1, capacity=10)
    start = 0
    for i in range(13):  # episodes of 4 steps with return 10 * their number: 0-3, 4-7, 8-11 (wraps), 12 running
        buffer.add([i], [0], 0.0, [i + 1], 0.0)
        if i % 4 == 3:
            buffer.end_episode(start, 10.0 * (i // 4))
            start = buffer.ptr
    torch.manual_seed(0)
    (obs, *_), returns = buffer.sample_finished(2000)
    assert set(obs[:, 0].tolist()) == set(range(3, 12))  # 0-2 overwritten, 12 still running
    torch.testing.assert_close(returns, 10.0 * (obs[:, 0] // 4))
    teacher = TeacherBuffer(capacity=100)
    teacher.add_episode(50.0, *episode_arrays(0, 40))
    teacher.add_episode(80.0, *episode_arrays(1, 40))
    obs, *_, returns = teacher.sample(500)
    torch.testing.assert_close(returns, torch.where(obs[:, 0] == 1, 80.0, 50.0))
    state = buffer.state_dict()
    copy = ReplayBuffer(obs_dim=1, act_dim=1, capacity=10)
    copy.load_state_dict(state)
    torch.testing.assert_close(copy.episode_returns, buffer.episode_returns, equal_nan=True)


def episode_arrays(value, length, obs_dim=3, act_dim=2):
    obs = np.full((length, obs_dim), value, np.float32)
    return obs, np.full((length, act_dim), value, np.float32), obs + 1, np.zeros(length, np.float32)


def test_promotion_rule_and_threshold():
    teacher = TeacherBuffer(capacity=100)
    teacher.add_episode(50.0, *episode_arrays(0, 40))
    teacher.add_episode(80.0, *episode_arrays(1, 40))
    assert teacher.threshold == 50.0 and teacher.num_episodes == 2
    assert not teacher.promote(50.0, *episode_arrays(2, 10))  # not strictly better
    assert not teacher.promote(10.0, *episode_arrays(2, 10))
    assert teacher.promote(60.0, *episode_arrays(3, 10))  # beats the worst kept return
    assert teacher.num_episodes == 3 and len(teacher) == 90 and teacher.threshold == 50.0
    # 90 + 40 > 100: the lowest-return episode (50) leaves, the threshold rises
    assert teacher.promote(70.0, *episode_arrays(4, 40))
    assert sorted(teacher.returns) == [60.0, 70.0, 80.0] and teacher.threshold == 60.0
    assert len(teacher) == 90
    obs, actions, next_obs, terminated, returns = teacher.sample(1000)
    assert set(obs[:, 0].tolist()) == {1.0, 3.0, 4.0}
    assert obs.dtype == torch.float32


def test_promotion_never_evicts_the_new_episode():
    teacher = TeacherBuffer(capacity=50)
    teacher.add_episode(10.0, *episode_arrays(0, 30))
    assert teacher.promote(20.0, *episode_arrays(1, 50))
    assert teacher.returns == [20.0] and teacher.threshold == 20.0


def test_pareto_keep_holds_a_short_fast_episode_beside_long_slow_ones():
    """The standing trap: a teacher that runs and falls (200 in 100 steps) against episodes that stand for the
    whole 1000 steps (1000-1040). By return alone the runner leaves R_E first. Kept by Pareto it stays, and the
    standing episode that the most others beat on both return and rate leaves instead; the runner leaves once
    faster episodes with more return beat it as often as the worst standing one (ties: the lower return)."""
    kept = {}
    for keep in ("return", "pareto"):
        teacher = TeacherBuffer(capacity=3000, keep=keep)
        teacher.add_episode(200.0, *episode_arrays(0, 100))
        for i, ret in enumerate([1000.0, 1020.0, 1040.0]):
            assert teacher.promote(ret, *episode_arrays(i + 1, 1000))
        kept[keep] = teacher.returns
    assert kept["return"] == [1000.0, 1020.0, 1040.0]
    assert kept["pareto"] == [200.0, 1020.0, 1040.0] and teacher.threshold == 200.0
    assert teacher.promote(2500.0, *episode_arrays(5, 1000))  # 2.5 per step: 1020 is beaten twice, leaves
    assert teacher.returns == [200.0, 1040.0, 2500.0]
    assert teacher.promote(2600.0, *episode_arrays(6, 1000))  # runner and 1040 beaten twice each: the lower leaves
    assert teacher.returns == [1040.0, 2500.0, 2600.0] and teacher.threshold == 1040.0


def test_pareto_keep_is_the_return_rule_where_episodes_have_one_length():
    """Same length, same rate order as return order: the two rules must keep the same episodes, ties included."""
    rng = np.random.default_rng(0)
    returns = rng.integers(0, 30, size=60).astype(float)  # integers: ties happen
    kept = {}
    for keep in ("return", "pareto"):
        teacher = TeacherBuffer(capacity=200, keep=keep)
        kept[keep] = []
        for i, ret in enumerate(returns):
            teacher.promote(ret, *episode_arrays(i, 50))
            kept[keep].append([float(t[0, 0]) for _, (t, *_) in teacher.episodes])
    assert kept["pareto"] == kept["return"]
    assert len({len(k) for k in kept["return"]}) > 1  # the buffer filled and promoted along the way


@pytest.mark.parametrize("alpha", [0.0, 0.25, 0.5, 1.0])
def test_mixed_sampling_proportions(alpha):
    teacher = TeacherBuffer(capacity=1000)
    teacher.add_episode(1.0, *episode_arrays(1.0, 100))
    self_buffer = ReplayBuffer(obs_dim=3, act_dim=2, capacity=100)
    for _ in range(50):
        self_buffer.add(np.zeros(3), np.zeros(2), 0.0, np.ones(3), 0.0)
    (obs, actions, next_obs, terminated), rewards, returns = mixed_batch(teacher, self_buffer, 256, alpha)
    assert returns is None
    assert obs.shape == (256, 3) and actions.shape == (256, 2) and terminated.shape == (256,)
    assert int((obs[:, 0] == 1.0).sum()) == round(alpha * 256)
    assert len(rewards) == 256 - round(alpha * 256)


# ---------------------------------------------------------------------------------------------
# demo files
# ---------------------------------------------------------------------------------------------

def recorded_episodes(env_id="Hopper-v5", n=3, seed=0):
    env = make_env(env_id, seed=seed, sparse=False, time_feature=False)
    return [rollout(env, lambda obs: env.action_space.sample()) for _ in range(n)]


def test_demo_file_round_trip(tmp_path):
    episodes = recorded_episodes()
    path = tmp_path / "demo.npz"
    save_demos(str(path), episodes, "Hopper-v5")
    assert os.listdir(tmp_path) == ["demo.npz"]  # the temp file was renamed away
    loaded = load_demos(str(path), "Hopper-v5", obs_dim=11, act_dim=3)
    assert len(loaded) == 3
    for ep, back in zip(episodes, loaded):
        np.testing.assert_allclose(back["observations"], ep["observations"], rtol=1e-6)
        np.testing.assert_allclose(back["next_observations"], ep["next_observations"], rtol=1e-6)
        np.testing.assert_array_equal(back["actions"], ep["actions"])
        assert back["terminated"] == ep["terminated"]
        assert back["episodic_return"] == pytest.approx(ep["episodic_return"])
        assert back["episodic_return"] == pytest.approx(float(np.sum(ep["rewards"])), rel=1e-5)
    assert len(load_demos(str(path), "Hopper-v5", 11, 3, num_demos=1)) == 1
    with np.load(path) as f:
        assert str(f["env_id"]) == "Hopper-v5" and f["terminations"].sum() == 3
        assert {"gymnasium_version", "mujoco_version"} <= set(f.files)


def test_a_mistyped_demo_path_without_minari_installed_says_it_is_not_a_demo_file(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "minari", None)  # import minari: ImportError
    with pytest.raises(ConfigError, match="demos/Hoper-v5 is not a demo file; as a Minari dataset id"):
        load_demos("demos/Hoper-v5", "Hopper-v5", 11, 3)
    with pytest.raises(ConfigError, match="^Minari datasets need the minari package"):
        load_demos(str(tmp_path), "Hopper-v5", 11, 3)  # a folder: only a Minari dataset could be meant


def test_each_bad_demo_file_gives_a_clear_error(tmp_path):
    path = str(tmp_path / "demo.npz")
    with pytest.raises(ConfigError, match="not found"):
        load_demos(path, "Hopper-v5", 11, 3)
    save_demos(path, recorded_episodes(), "Hopper-v5")
    with pytest.raises(ConfigError, match="for Hopper-v5, not Walker2d-v5"):
        load_demos(path, "Walker2d-v5", 17, 6)
    with pytest.raises(ConfigError, match="17-dim observations"):
        load_demos(path, "Hopper-v5", 17, 3)
    wide = dict(np.load(path))
    wide["next_observations"] = np.pad(wide["next_observations"], ((0, 0), (0, 1)))  # would fail 10k steps later
    np.savez(path, **wide)
    with pytest.raises(ConfigError, match="next_observations have shape"):
        load_demos(path, "Hopper-v5", 11, 3)
    save_demos(path, recorded_episodes(), "Hopper-v5")
    with pytest.raises(ConfigError, match="3 episodes, 4 were asked"):
        load_demos(path, "Hopper-v5", 11, 3, num_demos=4)
    with open(path, "r+b") as f:  # corrupt: truncated in the middle
        f.truncate(os.path.getsize(path) // 2)
    with pytest.raises(ConfigError, match="not a readable"):
        load_demos(path, "Hopper-v5", 11, 3)
    with open(path, "wb") as f:
        f.write(b"this is not a zip file")
    with pytest.raises(ConfigError, match="not a readable"):
        load_demos(path, "Hopper-v5", 11, 3)
    np.savez(path, observations=np.zeros((3, 11)))
    with pytest.raises(ConfigError, match="lacks actions"):
        load_demos(path, "Hopper-v5", 11, 3)
    save_demos(path, recorded_episodes(), "Hopper-v5")
    data = dict(np.load(path))
    data["episode_returns"][1] = np.nan  # the threshold would be nan: nothing could ever be promoted
    np.savez(path, **data)
    with pytest.raises(ConfigError, match="NaN"):
        load_demos(path, "Hopper-v5", 11, 3)
    with pytest.raises(ConfigError, match="is a folder"):
        load_demos(str(tmp_path), "Hopper-v5", 11, 3)
    for key, value in (("episode_returns", np.float64(3.0)), ("rewards", np.array(["a", "b"]))):
        np.savez(path, **(data | {key: value}))  # 0-d, or not numbers
        with pytest.raises(ConfigError, match=f"{key} must be arrays of numbers"):
            load_demos(path, "Hopper-v5", 11, 3)
    with open(path, "wb") as f:  # a plain .npy array under the .npz name
        np.save(f, np.zeros(3))
    with pytest.raises(ConfigError, match="not a readable"):
        load_demos(path, "Hopper-v5", 11, 3)
    np.savez_compressed(path, **data)
    raw = bytearray(open(path, "rb").read())
    raw[len(raw) // 2:len(raw) // 2 + 64] = bytes(64)  # damaged inside a compressed member: zlib's error
    open(path, "wb").write(bytes(raw))
    with pytest.raises(ConfigError, match="not a readable"):
        load_demos(path, "Hopper-v5", 11, 3)


def test_minari_datasets_round_trip_as_teacher_episodes(tmp_path, monkeypatch):
    """Episodes written as a Minari dataset (N+1 observations for N actions) load as the same
    transitions as the .npz demo file, by id from the local store and by folder; make_demos.py
    writes one; sail.py trains from one."""
    from demos import save_minari
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "store"))  # the subprocesses' store too
    episodes = recorded_episodes()
    save_minari("test/hopper/teacher-v0", episodes, "Hopper-v5")
    save_demos(str(tmp_path / "demo.npz"), episodes, "Hopper-v5")
    from_file = load_demos(str(tmp_path / "demo.npz"), "Hopper-v5", 11, 3)
    for source in ("test/hopper/teacher-v0", str(tmp_path / "store" / "test" / "hopper" / "teacher-v0")):
        loaded = load_demos(source, "Hopper-v5", 11, 3)
        assert len(loaded) == len(from_file) == 3
        for a, b in zip(loaded, from_file):
            for key in ("observations", "actions", "next_observations", "rewards"):
                np.testing.assert_array_equal(a[key], b[key])
            assert a["terminated"] == b["terminated"]
            assert a["episodic_return"] == pytest.approx(b["episodic_return"], rel=1e-9)
    with pytest.raises(ConfigError, match="for Hopper-v5, not Walker2d-v5"):
        load_demos("test/hopper/teacher-v0", "Walker2d-v5", 17, 6)
    with pytest.raises(ConfigError, match="local Minari store"):
        load_demos("test/hopper/nothing-v0", "Hopper-v5", 11, 3)
    made, trained = run_scripts(
        ("make_demos.py", "--env", "Hopper-v5", "--total-timesteps", "1500", "--learning-starts", "1000",
         "--eval-freq", "500", "--eval-episodes", "1", "--band", "-1000", "10000", "--num-episodes", "2",
         "--output", str(tmp_path / "made.npz"), "--minari", "test/hopper/made-v0"),
        ("sail.py", "--env", "Hopper-v5", "--demos", "test/hopper/teacher-v0", "--total-timesteps", "600",
         "--learning-starts", "300", "--eval-freq", "300", "--disc-freq", "100",
         "--output-dir", str(tmp_path), "--run-name", "run", *TINY))
    assert made.returncode == 0, made.stderr[-3000:]
    assert [ep["episodic_return"] for ep in load_demos("test/hopper/made-v0", "Hopper-v5", 11, 3)] == pytest.approx(
        [ep["episodic_return"] for ep in load_demos(str(tmp_path / "made.npz"), "Hopper-v5", 11, 3)])
    assert trained.returncode == 0 and "teacher: 1 episode," in trained.stdout, trained.stderr[-3000:]


def test_an_interrupted_minari_write_leaves_no_dataset_in_the_store(tmp_path, monkeypatch):
    import minari
    from demos import save_minari
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "store"))
    write = minari.create_dataset_from_buffers

    def write_then_interrupt(*args, **kwargs):  # Ctrl-C once Minari's files are on disk
        write(*args, **kwargs)
        raise KeyboardInterrupt
    monkeypatch.setattr(minari, "create_dataset_from_buffers", write_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        save_minari("test/hopper/teacher-v0", recorded_episodes(), "Hopper-v5")
    assert os.environ["MINARI_DATASETS_PATH"] == str(tmp_path / "store")
    assert os.listdir(tmp_path) == ["store"] and minari.list_local_datasets() == {}
    with pytest.raises(ConfigError, match="local Minari store"):
        load_demos("test/hopper/teacher-v0", "Hopper-v5", 11, 3)
    monkeypatch.setattr(minari, "create_dataset_from_buffers", write)
    save_minari("test/hopper/teacher-v0", recorded_episodes(), "Hopper-v5")
    assert list(minari.list_local_datasets()) == ["test/hopper/teacher-v0"] and os.listdir(tmp_path) == ["store"]


@pytest.mark.parametrize("env_id", sorted(SHIPPED))
def test_shipped_demos_load_and_are_sub_optimal(env_id):
    env = make_env(env_id, seed=0, time_feature=False)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    for name, (low, high) in SHIPPED[env_id].items():
        episodes = load_demos(os.path.join(HERE, "demos", f"{name}.npz"), env_id, obs_dim, act_dim)
        assert len(episodes) == 10
        for ep in episodes:
            assert low <= ep["episodic_return"] <= high
            assert ep["episodic_return"] == pytest.approx(float(np.sum(ep["rewards"], dtype=np.float64)), rel=1e-4)


# ---------------------------------------------------------------------------------------------
# td3.py and make_demos.py
# ---------------------------------------------------------------------------------------------

def test_td3_learns_a_one_step_bandit():
    """Reward = -(a - 0.5)^2, every transition terminal: the actor must move toward 0.5."""
    torch.manual_seed(0)
    agent = TD3(obs_dim=1, act_dim=1, action_low=[-1.0], action_high=[1.0], hidden=(32, 32), lr=3e-3)
    obs = torch.zeros(128, 1)
    for _ in range(600):
        actions = torch.rand(128, 1) * 2 - 1
        rewards = -(actions[:, 0] - 0.5) ** 2
        agent.update(obs, actions, rewards, obs, torch.ones(128))
    assert abs(float(agent.act(np.zeros(1))[0]) - 0.5) < 0.1


@pytest.mark.parametrize("activation", [None, "relu", "tanh"])
def test_onednn_linear_equals_f_linear_up_to_second_derivatives(activation):
    """cpu_kernels.linear (oneDNN) computes what F.linear and the activation do: outputs with and
    without autograd (the fused kernel), gradients, and gradients of gradients."""
    torch.manual_seed(0)
    x, weight, bias = torch.randn(64, 24), torch.randn(32, 24) / 5, torch.randn(32)
    act = {None: lambda y: y, "relu": F.relu, "tanh": torch.tanh}[activation]
    plain = lambda x, w, b: act(F.linear(x, w, b))  # noqa: E731
    fast = lambda x, w, b: cpu_kernels.linear(x, w, b, activation)  # noqa: E731
    with torch.no_grad():
        torch.testing.assert_close(fast(x, weight, bias), plain(x, weight, bias), rtol=1e-4, atol=1e-5)
    results = []
    for fn in (fast, plain):
        inputs = [t.clone().requires_grad_(True) for t in (x, weight, bias)]
        out = fn(*inputs)
        loss = torch.sin(out).sum()
        grads = torch.autograd.grad(loss, inputs, create_graph=True)
        # as in the gradient penalty: a loss on the input gradient, differentiated again
        grads_of_grads = torch.autograd.grad(grads[0].norm(dim=1).sub(1).pow(2).mean(), inputs[:2])
        results.append((out, *grads, *grads_of_grads))
    graph = {results[0][0].grad_fn}
    while not any("OneDNNLinear" in type(g).__name__ for g in graph):  # the fast path was taken
        graph = {f for g in graph for f, _ in g.next_functions if f is not None}
        assert graph, "cpu_kernels.linear did not use OneDNNLinearFunction"
    for fast_result, plain_result in zip(*results):
        torch.testing.assert_close(fast_result, plain_result, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("kernels", ["torch", "onednn"])
def test_td3_update_equals_the_straightforward_formulas(kernels):
    """One TD3.update (with either CPU kernels: fused oneDNN layers or plain torch; fixed-Q1 actor
    step, fused Adam, foreach Polyak) against the TD3 formulas written out on plain copies."""
    torch.manual_seed(0)
    low, high = torch.tensor([-1.0, -2.0]), torch.tensor([1.0, 2.0])
    agent = TD3(obs_dim=5, act_dim=2, action_low=low, action_high=high, hidden=(64, 64), policy_delay=1)
    obs, next_obs = torch.randn(128, 5), torch.randn(128, 5)
    actions = (torch.rand(128, 2) * 2 - 1) * high
    rewards, terminated = torch.randn(128), (torch.rand(128) < 0.2).float()
    actor, critic = copy.deepcopy(agent.actor), copy.deepcopy(agent.critic)
    actor_target, critic_target = copy.deepcopy(agent.actor_target), copy.deepcopy(agent.critic_target)
    cpu_kernels.apply(kernels, agent.networks())
    if kernels == "onednn":  # the fast path is really taken
        assert any(isinstance(m, cpu_kernels.OneDNNLinear) and m.activation == "relu" for m in agent.critic.modules())

    torch.manual_seed(1)
    losses = agent.update(obs, actions, rewards, next_obs, terminated)

    torch.manual_seed(1)
    noise = (torch.randn_like(actions) * 0.2 * high).clamp(-0.5 * high, 0.5 * high)
    with torch.no_grad():
        next_actions = torch.max(torch.min(actor_target(next_obs) + noise, high), low)
        q1_next, q2_next = critic_target(next_obs, next_actions)
        y = rewards + 0.99 * (1 - terminated) * torch.min(q1_next, q2_next)
    q1, q2 = critic(obs, actions)
    critic_loss = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
    critic_grads = torch.autograd.grad(critic_loss, list(critic.parameters()))
    torch.testing.assert_close(losses["critic_loss"], critic_loss.detach(), rtol=1e-5, atol=1e-6)
    for fast, plain in zip(agent.critic.parameters(), critic_grads):  # the actor step left them alone
        torch.testing.assert_close(fast.grad, plain, rtol=1e-4, atol=1e-6)

    updated_critic = copy.deepcopy(agent.critic)  # the actor step uses the critic after its step
    actor_loss = -updated_critic(obs, actor(obs))[0].mean()
    actor_grads = torch.autograd.grad(actor_loss, list(actor.parameters()))
    torch.testing.assert_close(losses["actor_loss"], actor_loss.detach(), rtol=1e-5, atol=1e-6)
    for fast, plain in zip(agent.actor.parameters(), actor_grads):
        torch.testing.assert_close(fast.grad, plain, rtol=1e-4, atol=1e-6)

    for online, old_target, new_target in ((agent.actor, actor_target, agent.actor_target),
                                           (agent.critic, critic_target, agent.critic_target)):
        for p, old, new in zip(online.parameters(), old_target.parameters(), new_target.parameters()):
            torch.testing.assert_close(new, 0.995 * old + 0.005 * p)


def test_explore_adds_gaussian_noise_of_the_exploration_noise_std_drawn_from_rng():
    agent = TD3(12, 3, -np.ones(3), np.ones(3), hidden=(32, 32))
    obs = np.zeros(12, dtype=np.float32)
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    np.testing.assert_allclose(agent.explore(obs, 0.1, a), np.clip(agent.act(obs) + b.normal(0, 0.1, 3), -1, 1),
                               rtol=1e-6)


def test_td3_target_takes_the_zero_action_where_the_next_action_mask_is_zero():
    """DAC's absorbing state admits only the zero action: there the target is r + gamma Q'(s', 0),
    whatever the target actor and the smoothing noise would give; elsewhere it is unchanged."""
    torch.manual_seed(0)
    agent = TD3(obs_dim=5, act_dim=2, action_low=-torch.ones(2), action_high=torch.ones(2), hidden=(64, 64))
    obs, next_obs, actions = torch.randn(128, 5), torch.randn(128, 5), torch.rand(128, 2) * 2 - 1
    rewards, terminated = torch.randn(128), torch.zeros(128)
    mask = (torch.arange(128) % 2).float()[:, None]  # every other next state is "absorbing"
    critic, actor_target, critic_target = (copy.deepcopy(m) for m in (agent.critic, agent.actor_target,
                                                                      agent.critic_target))
    torch.manual_seed(1)
    masked = agent.update(obs, actions, rewards, next_obs, terminated, next_action_mask=mask)["critic_loss"]

    torch.manual_seed(1)
    noise = (torch.randn_like(actions) * 0.2).clamp(-0.5, 0.5)
    with torch.no_grad():
        q1, q2 = critic(obs, actions)
        losses = []
        for next_actions in ((actor_target(next_obs) + noise).clamp(-1.0, 1.0) * m for m in (mask, 1.0)):
            y = rewards + 0.99 * torch.min(*critic_target(next_obs, next_actions))
            losses.append(((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean())
    torch.testing.assert_close(masked, losses[0], rtol=1e-5, atol=1e-6)
    assert abs(losses[0] - losses[1]) > 1e-4  # without the mask the target would differ


def test_make_demos_smoke_run_writes_a_loadable_file(tmp_path):
    out = tmp_path / "Hopper-v5.npz"
    proc = run_script("make_demos.py", "--env", "Hopper-v5", "--total-timesteps", "1500",
                      "--learning-starts", "1000", "--eval-freq", "500", "--eval-episodes", "1",
                      "--band", "-1000", "10000", "--num-episodes", "2", "--output", str(out))
    assert proc.returncode == 0, proc.stderr
    assert len(load_demos(str(out), "Hopper-v5", 11, 3)) == 2


def test_make_demos_bad_input_is_one_line(tmp_path, capsys):
    import make_demos
    *procs, unknown = [main_in_process(make_demos.main, argv, capsys) for argv in (
        ["--env", "NoSuchEnv-v5", "--band", "0", "1"], ["--env", "Hopper-v5", "--num-episodes", "0"],
        ["--env", "Pendulum-v1"],  # no default band
        ["--env", "Hopper-v5", "--seed", "-1"], ["--env", "Hopper-v5", "--exploration-noise", "-0.1"],
        ["--env", "Hopper-v5", "--lr", "-1"], ["--env", "Hopper-v5", "--gamma", "-5"],
        ["--env", "Hopper-v5", "--band", "nan", "nan"],  # would fail only after the whole training budget
        ["--env", "Hopper-v5", "--output", HERE, "--force"],  # a folder
        ["--env", "Hopper-v5", "--output", str(tmp_path / "d.npz"), "--minari", "no-version"],
        ["--env", "NoSuchEnv-v5"])]  # not reported as a missing band
    for proc in procs + [unknown]:
        assert_one_line_error(proc)
    assert "unknown environment" in unknown.stderr


def test_make_demos_resumed_from_a_checkpoint_continues_the_same_run(tmp_path):
    """A checkpoint at an evaluation step is written after that evaluation, which draws start
    states from the eval env: a run resumed from it goes on as the run that wrote it did."""
    def command(checkpoint, every):
        return ("make_demos.py", "--env", "Hopper-v5", "--total-timesteps", "1500", "--learning-starts", "500",
                "--eval-freq", "500", "--eval-episodes", "2", "--hidden", "16", "16",
                "--band", "1e6", "1e7",  # unreachable: evaluations at 1000 and 1500, then the one-line error
                "--checkpoint", str(tmp_path / checkpoint), "--checkpoint-freq", every,
                "--output", str(tmp_path / "never.npz"))
    straight, stopped = run_scripts(command("a.pt", "500"), command("b.pt", "1000"), at_once=2)
    resumed = run_script(*command("b.pt", "500"))  # from b.pt's step 1000, as after a crash there
    assert straight.returncode == stopped.returncode == resumed.returncode == 1, resumed.stderr[-3000:]
    assert "resumed from" in resumed.stdout

    def flat(state, prefix=""):
        items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, list) else None
        if items is None:
            return {prefix: state}
        return {k: v for key, value in items for k, v in flat(value, f"{prefix}/{key}").items()}
    a, b = (flat(torch.load(tmp_path / name, weights_only=False)) for name in ("a.pt", "b.pt"))
    assert a.keys() == b.keys() and a["/global_step"] == 1500 and any("eval_env" in k for k in a)
    for key in (k for k in a if not k.endswith("episode_start_time")):  # wall clock (RecordEpisodeStatistics)
        x, y = np.asarray(a[key]), np.asarray(b[key])
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), key


def test_make_demos_unreadable_checkpoint_is_one_line(tmp_path, capsys):
    import make_demos
    broken = tmp_path / "teacher.pt"
    broken.write_text("not a checkpoint")
    assert_one_line_error(main_in_process(make_demos.main, ["--env", "Hopper-v5", "--checkpoint", str(broken),
                                                            "--output", str(tmp_path / "out.npz")], capsys))
    assert not (tmp_path / "out.npz").exists()


def test_make_demos_refuses_a_checkpoint_written_with_other_flags(tmp_path, capsys):
    """Continuing another run's checkpoint (another seed, env or step size) would train neither run:
    one error line naming the flags, before any training; flags that only say where outputs go may change."""
    import make_demos
    checkpoint = tmp_path / "teacher.pt"

    def run(*flags):
        return main_in_process(make_demos.main, [
            "--env", "Hopper-v5", "--total-timesteps", "600", "--learning-starts", "500", "--eval-freq", "500",
            "--eval-episodes", "1", "--hidden", "16", "16", "--band", "1e6", "1e7", "--checkpoint", str(checkpoint),
            "--checkpoint-freq", "500", *flags], capsys)
    first = run("--output", str(tmp_path / "a.npz"))
    assert first.returncode == 1 and "did not reach the band" in first.stderr  # after a checkpoint at step 500
    written = checkpoint.stat().st_mtime_ns
    other = run("--output", str(tmp_path / "b.npz"), "--seed", "1", "--lr", "0.001")
    assert_one_line_error(other)
    assert "--seed 0, not --seed 1" in other.stderr and "--lr 0.0003, not --lr 0.001" in other.stderr
    assert checkpoint.stat().st_mtime_ns == written
    same = run("--output", str(tmp_path / "c.npz"), "--threads", "2")  # the same run, elsewhere, faster
    assert same.returncode == 1 and "resumed from" in same.stdout and "did not reach the band" in same.stderr


def test_make_demos_checks_its_outputs_before_training_and_never_overwrites_without_force(tmp_path):
    import make_demos
    from demos import default_demo_path
    assert make_demos.parse_args(["--env", "Hopper-v5"]).output == default_demo_path("Hopper-v5")  # not cwd-relative
    shipped = default_demo_path("Hopper-v5")
    before = os.path.getmtime(shipped)
    assert_one_line_error(run_script("make_demos.py", "--env", "Hopper-v5"))  # the shipped file exists
    assert os.path.getmtime(shipped) == before
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for flag in ("--output", "--checkpoint"):
        other = "--checkpoint" if flag == "--output" else "--output"
        proc = run_script("make_demos.py", "--env", "Hopper-v5", flag, str(blocker / "x"), other, str(tmp_path / "y"),
                          "--learning-starts", "10", "--total-timesteps", "100000000", timeout=60)
        assert_one_line_error(proc)  # at once: a training of 1e8 steps would not end within the timeout
        assert "cannot write" in proc.stderr


def test_make_demos_stops_on_sigterm_with_a_checkpoint_that_continues(tmp_path):
    import signal
    import time
    checkpoint = tmp_path / "teacher.pt"
    command = ["make_demos.py", "--env", "Hopper-v5", "--total-timesteps", "100000000",
               "--learning-starts", "100", "--eval-freq", "1000000", "--hidden", "16", "16",
               "--checkpoint", str(checkpoint), "--checkpoint-freq", "1000000", "--output", str(tmp_path / "d.npz")]
    out_path, err_path = tmp_path / "out", tmp_path / "err"

    def start_then_stop(signum):
        """Starts the command, waits for its training loop (where the stop handler is in place: on a
        loaded machine the imports alone can take seconds), lets it run, stops it: stdout, stderr."""
        for path in (out_path, err_path):  # the first run's output would pass for the second's until it starts
            path.unlink(missing_ok=True)
        proc = start_script(command, out_path, err_path)
        deadline = time.time() + 120
        while not (out_path.exists() and "training the teacher" in out_path.read_text()):
            assert proc.is_alive() and time.time() < deadline, err_path.read_text()[-3000:]  # ended before its loop
            time.sleep(0.05)
        time.sleep(1)
        os.kill(proc.pid, signum)
        proc.join(60)
        return proc.exitcode, out_path.read_text(), err_path.read_text()

    code, out, err = start_then_stop(signal.SIGTERM)
    assert code == 143 and "Traceback" not in err, err[-3000:]
    step = torch.load(checkpoint, weights_only=True)["global_step"]
    assert step > 0 and f"stopped at step {step}" in out
    code, out, err = start_then_stop(signal.SIGINT)
    assert code == 130 and f"resumed from {checkpoint} at step {step}" in out, err[-3000:]
    assert torch.load(checkpoint, weights_only=True)["global_step"] >= step


def test_bernoulli_entropy_is_the_closed_form():
    logits = torch.linspace(-30, 30, 601)
    closed_form = F.softplus(-logits) + (1 - torch.sigmoid(logits)) * logits
    torch.testing.assert_close(torch.distributions.Bernoulli(logits=logits).entropy(), closed_form)


def test_auto_kernels_choose_without_touching_the_run_rng_and_keep_the_networks_interchangeable():
    from discriminator import Discriminator
    torch.manual_seed(0)
    disc = Discriminator(obs_dim=5, act_dim=2, hidden=[64, 64])
    state = torch.get_rng_state()
    assert cpu_kernels.choose("auto", [disc.net], 128, "cpu") in ("torch", "onednn")
    assert torch.equal(torch.get_rng_state(), state)
    fast = copy.deepcopy(disc)
    cpu_kernels.apply("onednn" if cpu_kernels.AVAILABLE else "torch", [fast])
    assert fast.state_dict().keys() == disc.state_dict().keys()
    x = torch.randn(128, 7)
    torch.testing.assert_close(fast(x), disc(x), rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# sail.py
# ---------------------------------------------------------------------------------------------

import csv  # noqa: E402
import json  # noqa: E402

import sail  # noqa: E402
from credit import RewardModel, decomposition_unit, train_reward_model  # noqa: E402
from discriminator import Discriminator, discriminator_loss, shaped_reward  # noqa: E402
from plumbing import PROGRESS_COLUMNS  # noqa: E402

TINY = ["--hidden", "32", "32", "--disc-hidden", "32", "32", "--threads", "1", "--eval-episodes", "1"]


def read_csv(run_dir):
    with open(os.path.join(run_dir, "progress.csv")) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def poor_hopper_demos(tmp_path_factory):
    """Hopper episodes of a deliberately poor 'teacher': the worst of 30 random episodes."""
    env = make_env("Hopper-v5", seed=0, sparse=False, time_feature=False)
    episodes = sorted((rollout(env, lambda obs: env.action_space.sample()) for _ in range(30)),
                      key=lambda ep: ep["episodic_return"])
    path = str(tmp_path_factory.mktemp("demos") / "Hopper-v5.npz")
    save_demos(path, episodes[:4], "Hopper-v5")
    return path


def test_sail_reward_is_softplus_of_the_logit_without_overflow():
    logits = torch.tensor([-50.0, -3.0, 0.0, 3.0, 15.0])
    torch.testing.assert_close(F.softplus(logits), -torch.log(1 - torch.sigmoid(logits.double())).float())
    disc = Discriminator(obs_dim=1, act_dim=1, hidden=[8])
    with torch.no_grad():
        disc.net[-1].bias.fill_(1000.0)  # a saturated D: sigmoid(logit) == 1.0 in float32
    reward = shaped_reward(disc, torch.zeros(4, 1), torch.zeros(4, 1), "sail")
    assert torch.isfinite(reward).all() and (reward > 900).all()


def _train_discriminator(disc, teacher, agent, steps):
    """`steps` minibatches of Eq. (4) on samplers n -> (obs, actions); returns the last D means."""
    optimizer = torch.optim.Adam(disc.parameters(), lr=1e-3)
    for _ in range(steps):
        (t_obs, t_act), (b_obs, b_act) = teacher(128), agent(128)
        disc.update_norms(torch.cat([t_obs, b_obs]), torch.cat([t_act, b_act]))
        loss, d_teacher, d_self = discriminator_loss(disc, t_obs, t_act, b_obs, b_act, 0.01, 10.0)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return d_teacher, d_self


def test_disc_action_norm_lets_d_tell_teacher_from_agent_by_the_size_of_their_actions():
    """States alike, the agent's actions 0.1 larger than the teacher's (std 0.05 each): under the gradient
    penalty, D on the actions as they are stays at 0.5 for both; on normalised actions it separates them."""
    teacher = lambda n: (torch.randn(n, 4), torch.randn(n, 2) * 0.05 + 0.1)  # noqa: E731
    agent = lambda n: (torch.randn(n, 4), torch.randn(n, 2) * 0.05 + 0.2)  # noqa: E731
    gaps = {}
    for action_norm in (False, True):
        torch.manual_seed(0)
        disc = Discriminator(obs_dim=4, act_dim=2, hidden=[32, 32], action_norm=action_norm)
        _train_discriminator(disc, teacher, agent, 500)
        with torch.no_grad():
            d = [torch.sigmoid(disc(disc.inputs(*sample(2000)))).mean().item() for sample in (teacher, agent)]
        gaps[action_norm] = d[0] - d[1]
    assert abs(gaps[False]) < 0.1
    assert gaps[True] > 0.2


def test_discriminator_rewards_teacher_data_more_after_training():
    torch.manual_seed(0)
    disc = Discriminator(obs_dim=4, act_dim=2, hidden=[32, 32])
    teacher = lambda n: (torch.randn(n, 4) + 2.0, torch.rand(n, 2) * 0.5 + 0.5)  # noqa: E731
    agent = lambda n: (torch.randn(n, 4) - 2.0, torch.rand(n, 2) * 0.5 - 1.0)  # noqa: E731
    d_teacher, d_self = _train_discriminator(disc, teacher, agent, 200)
    assert d_teacher > 0.7 and d_self < 0.3
    assert shaped_reward(disc, *teacher(500), "sail").mean() > 3 * shaped_reward(disc, *agent(500), "sail").mean()


SMOKE = {
    # D's negatives: all of R_B until the first promotion (here before learning starts), then recent ones
    "sail": ["--kernels", "torch"],
    "sail-paper": ["--algo", "sail-paper"],
    "fixed-alpha": ["--fixed-alpha"],
    "no-lfd": ["--alpha", "0"],
    "no-adaptation": ["--no-adaptation", "--disc-negatives", "all", "--kernels", "torch"],
    "recent-negatives": ["--disc-negatives", "recent", "--kernels", "torch"],  # the paper's SAIL-OnPolicy
    # the default D's negatives without adaptation: no promotion, so all of R_B throughout
    "recent-after-promotion-no-adaptation": ["--no-adaptation", "--kernels", "torch"],
    "no-return-bonus": ["--return-bonus", "0"],
    "dac": ["--algo", "dac"],
    "td3": ["--algo", "td3"],
    "ircr": ["--algo", "ircr"],
    "rrd": ["--algo", "rrd", "--decomposition-subset", "16", "--method", "RRD (K 16)"],
    "decomposition": ["--decomposition-subset", "16", "--decomposition-unit", "range", "--action-cost", "reward",
                      "--kernels", "onednn" if cpu_kernels.AVAILABLE else "torch"],
    "bc": ["--bc-steps", "300", "--eval-freq", "100"],  # bc.py, with the run-folder flags of sail.py
}


def sail_update(agent, disc, teacher_buffer, self_buffer, alpha, args, return_range, reward_model=None, unit=1.0):
    """sail.py's update on the given parts: with a reward model, one minibatch of it (here at a learning
    rate of 0, so that it stays as the test set it), then one TD3 step with the reward r'."""
    parts = {"agent": agent, "disc": disc, "teacher_buffer": teacher_buffer, "self_buffer": self_buffer}
    if reward_model is not None:
        parts |= {"reward_model": reward_model, "reward_optimizer": torch.optim.SGD(reward_model.parameters(), lr=0.0)}
    state = sail.LoopState(alpha=alpha, kernels="torch", return_range=return_range)
    return sail.update(parts, state, args, unit)


def test_return_bonus_adds_the_scaled_episodic_return_to_the_critic_reward():
    import argparse
    agent = TD3(obs_dim=3, act_dim=2, action_low=-np.ones(2), action_high=np.ones(2), hidden=(16, 16))
    disc = Discriminator(3, 2, [16])
    self_buffer = ReplayBuffer(obs_dim=3, act_dim=2, capacity=100)
    for i in range(40):
        self_buffer.add(np.full(3, i), np.zeros(2), 0.0, np.full(3, i + 1), 0.0)
    self_buffer.end_episode(0, 7.0)
    means = {}
    for bonus in (0.0, 2.0):
        torch.manual_seed(0)  # the same batch both times: the bonus draws no extra samples here
        args = argparse.Namespace(batch_size=64, reward="sail", return_bonus=bonus, absorbing=False,
                                  return_decomposition=0.0, action_cost="none")
        means[bonus] = float(sail_update(copy.deepcopy(agent), disc, TeacherBuffer(10), self_buffer, 0.0, args,
                                        return_range=(2.0, 12.0))["reward_mean"])
    assert means[2.0] - means[0.0] == pytest.approx(2.0 * (7.0 - 2.0) / (12.0 - 2.0), abs=1e-5)
    # IRCR (--reward none): the bonus is the whole reward, D plays no part
    args = argparse.Namespace(batch_size=64, reward="none", return_bonus=2.0, absorbing=False,
                              return_decomposition=0.0, action_cost="none", decomposition_subset=16)
    ircr = sail_update(copy.deepcopy(agent), disc, TeacherBuffer(10), self_buffer, 0.0, args, return_range=(2.0, 12.0))
    assert float(ircr["reward_mean"]) == pytest.approx(2.0 * (7.0 - 2.0) / (12.0 - 2.0), abs=1e-6)
    # return decomposition: a reward model that says 0.5 everywhere adds 3 * 0.5 / ((12 - 2) / 40) per step
    model = RewardModel(3, 2, [16])
    torch.nn.init.zeros_(model.net[-1].weight)
    torch.nn.init.constant_(model.net[-1].bias, 0.5)
    args.return_bonus, args.return_decomposition = 0.0, 3.0
    unit = decomposition_unit("range", (2.0, 12.0), (0.5, 3.0), episode_steps=40)
    rrd = sail_update(copy.deepcopy(agent), disc, TeacherBuffer(10), self_buffer, 0.0, args, return_range=(2.0, 12.0),
                     reward_model=model, unit=unit)
    assert float(rrd["reward_mean"]) == pytest.approx(3.0 * 0.5 / (10.0 / 40), abs=1e-5)
    # --decomposition-unit rate: per-step returns 0.5 to 3.0 seen, whatever the time limit
    assert decomposition_unit("rate", (2.0, 12.0), (0.5, 3.0), episode_steps=40) == pytest.approx(2.5)


class _QuadraticQ(torch.nn.Module):
    """Q(s, a) = offset - |a - best|^2: a critic whose best action is known."""
    def __init__(self, best, offset=0.0):
        super().__init__()
        self.best = torch.nn.Parameter(torch.as_tensor(best, dtype=torch.float32))
        self.offset = offset

    def forward(self, obs, action):
        return self.offset - ((action - self.best) ** 2).sum(-1)


def test_action_cost_moves_the_actor_to_the_best_action_of_q_minus_the_cost():
    """Q(s, a) = -|a - 0.6|^2 per dimension: charged c |a|^2 beside it, the actor's best action is
    0.6 / (1 + c), 0.3 for c = 1; a cost of 0 leaves it at Q's 0.6."""
    torch.manual_seed(0)
    obs = torch.randn(64, 3)
    final = {}
    for cost in (0.0, 1.0):
        agent = TD3(obs_dim=3, act_dim=2, action_low=-np.ones(2), action_high=np.ones(2), hidden=(16, 16),
                    policy_delay=1, lr=1e-2)
        agent.critic.q1, agent.critic.q2 = _QuadraticQ([0.6, 0.6]), _QuadraticQ([0.6, 0.6])
        for _ in range(200):
            agent.update(obs, torch.zeros(64, 2), torch.zeros(64), obs, torch.zeros(64),
                         actor_penalty=lambda actions: cost * actions.pow(2).sum(-1))
        final[cost] = agent.actor(obs).mean().item()
    assert final[0.0] == pytest.approx(0.6, abs=0.03)
    assert final[1.0] == pytest.approx(0.3, abs=0.03)


def test_actor_action_cost_charges_the_learned_cost_over_the_decomposition_unit():
    """sail.py's update with --action-cost reward-and-actor: the reward model's learned c (here 2, softplus
    of its parameter) over the unit (2) and times --return-decomposition (1) charges the actor 1 x ||a||^2,
    so against Q = -|a - 0.6|^2 its action goes to 0.3; with --action-cost reward it stays at Q's 0.6."""
    import argparse
    self_buffer = ReplayBuffer(obs_dim=3, act_dim=2, capacity=100)
    rng = np.random.default_rng(0)
    for i in range(40):
        self_buffer.add(rng.normal(size=3), np.zeros(2), 0.0, rng.normal(size=3), 0.0)
    self_buffer.end_episode(0, 1.0)
    model = RewardModel(3, 2, [8], learn_action_cost=True)
    with torch.no_grad():
        model.action_cost_rho.fill_(float(np.log(np.expm1(2.0))))  # softplus^-1(2)
    final = {}
    for charged in (False, True):
        torch.manual_seed(0)
        agent = TD3(obs_dim=3, act_dim=2, action_low=-np.ones(2), action_high=np.ones(2), hidden=(16, 16),
                    policy_delay=1, lr=1e-2)
        agent.critic.q1, agent.critic.q2 = _QuadraticQ([0.6, 0.6]), _QuadraticQ([0.6, 0.6])
        args = argparse.Namespace(batch_size=64, reward="none", return_bonus=0.0, absorbing=False,
                                  return_decomposition=1.0, decomposition_subset=16,
                                  action_cost="reward-and-actor" if charged else "reward")
        for _ in range(200):
            sail_update(agent, None, TeacherBuffer(10), self_buffer, 0.0, args, return_range=(0.0, 1.0),
                       reward_model=model, unit=2.0)
        final[charged] = agent.actor(self_buffer.obs[:40]).mean().item()
    assert final[False] == pytest.approx(0.6, abs=0.03)
    assert final[True] == pytest.approx(0.3, abs=0.03)


def test_episode_subsets_hold_steps_of_one_finished_episode_and_mask_overwritten_ones():
    buffer = ReplayBuffer(obs_dim=1, act_dim=1, capacity=20)
    start = 0
    for i in range(27):  # episodes 0-9 (return 0; its 0-6 overwritten), 10-14 (return 1), 15-24 (2, wraps), 25- running
        buffer.add([i], [0], 0.0, [i + 1], 0.0)
        if i in (9, 14, 24):
            buffer.end_episode(start, {9: 0.0, 14: 1.0, 24: 2.0}[i])
            start = buffer.ptr
    torch.manual_seed(0)
    obs, actions, next_obs, mask, returns, lengths = buffer.sample_episode_subsets(300, 8)
    assert obs.shape == (300, 8, 1) and mask.shape == (300, 8)
    assert set(lengths.tolist()) == {10, 5} and set(returns.tolist()) == {0.0, 1.0, 2.0}
    first = {0.0: range(0, 10), 1.0: range(10, 15), 2.0: range(15, 25)}
    for episode, kept, ret in zip(obs[..., 0], mask, returns.tolist()):  # kept steps: the anchor's episode
        assert all(int(x) in first[ret] for x, m in zip(episode, kept) if m)
    kept = obs[..., 0][mask.bool()]
    assert kept.min() >= 7 and set(kept.tolist()) == set(range(7, 25))  # 0-6 overwritten, 25-26 running
    for episode, kept, ret in zip(obs[..., 0], mask, returns.tolist()):  # distinct steps; a short episode whole
        steps = episode[kept.bool()].tolist()
        assert len(set(steps)) == len(steps) and (ret != 1.0 or sorted(steps) == list(range(10, 15)))
        assert ret != 2.0 or len(steps) == 8
    assert (mask[returns == 0.0] == 0).any()
    # a subset at least as long as the episodes (K >= T): each row holds its whole episode, padding masked
    obs, _, _, mask, returns, lengths = buffer.sample_episode_subsets(100, 30)
    assert obs.shape == (100, 30, 1) and (mask.sum(1)[returns > 0] == lengths[returns > 0]).all()
    for episode, kept, ret in zip(obs[..., 0], mask, returns.tolist()):
        assert ret == 0.0 or sorted(episode[kept.bool()].tolist()) == list(first[ret])
    copy = ReplayBuffer(obs_dim=1, act_dim=1, capacity=20)
    copy.load_state_dict(buffer.state_dict())
    assert torch.equal(copy.episode_starts, buffer.episode_starts) and torch.equal(copy.episode_lengths,
                                                                                    buffer.episode_lengths)


def made_up_episodes(rng, act_dim, per_step_reward, act_scale=1.0):
    """A self buffer of about 4900 steps in episodes of 2 to 16 steps: states uniform in [-1, 1]^2
    (s' = s), actions uniform in [-1, 1]^act_dim times act_scale times a factor drawn per episode
    (how hard it acts); of the hidden per_step_reward(obs, actions) only each episode's sum is stored."""
    buffer = ReplayBuffer(obs_dim=2, act_dim=act_dim, capacity=5000)
    while buffer.size < 4900:
        start, length = buffer.ptr, int(rng.integers(2, 17))
        obs = rng.uniform(-1, 1, (length, 2)).astype(np.float32)
        actions = (act_scale * rng.uniform(0, 1) * rng.uniform(-1, 1, (length, act_dim))).astype(np.float32)
        for o, a in zip(obs, actions):
            buffer.add(o, a, 0.0, o, 0.0)
        buffer.end_episode(start, float(per_step_reward(obs, actions).sum()))
    return buffer


def test_return_decomposition_recovers_a_per_step_reward_from_episodic_returns():
    """Episodes of 2 to 16 steps whose hidden per-step reward is 2 * obs[0] - 1: only each
    episode's sum is stored, and the reward model learns the per-step reward from the sums."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    buffer = made_up_episodes(rng, 1, lambda obs, actions: 2 * obs[:, 0] - 1, act_scale=0.0)
    model = RewardModel(2, 1, [32, 32])
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(1500):
        loss = train_reward_model(model, optimizer, buffer, 256, 16)["decomposition_loss"]
    probe = torch.tensor(rng.uniform(-1, 1, (500, 2)), dtype=torch.float32)
    learned = model(probe, torch.zeros(500, 1), probe).detach()
    assert float(loss) < 0.05
    assert torch.corrcoef(torch.stack([learned, 2 * probe[:, 0] - 1]))[0, 1] > 0.95
    assert float((learned - (2 * probe[:, 0] - 1)).abs().mean()) < 0.2


@pytest.mark.parametrize("cost_weight", [0.5, 0.0])
def test_decomposition_action_cost_learns_the_weight_of_a_quadratic_control_cost(cost_weight):
    """Episodes whose hidden per-step reward is 2 * obs[0] - 1 - cost_weight * ||a||^2 (8 action
    dimensions), with how hard each episode acts drawn per episode, and a network too small to fit
    the quadratic itself (on Ant-v5 the runs' networks learned only part of it from episode sums):
    c, learned from the sums alone, comes near the hidden weight, and stays near 0 where the actions
    cost nothing."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    buffer = made_up_episodes(rng, 8, lambda obs, actions: 2 * obs[:, 0] - 1 - cost_weight * (actions ** 2).sum(1))
    model = RewardModel(2, 8, [4], learn_action_cost=True)
    optimizer = torch.optim.Adam(model.parameter_groups(3e-3))
    for _ in range(1500):
        stats = train_reward_model(model, optimizer, buffer, 256, 16)
    assert float(stats["decomposition_loss"]) < 0.05
    assert float(stats["decomposition_action_cost"]) == pytest.approx(cost_weight, abs=0.15)


def test_a_reward_model_saved_before_the_learned_action_cost_loads_without_it():
    """Runs saved before the learned action cost resume: without it (--action-cost none) the reward model and
    its optimizer (one parameter group, as make_adam(model.parameters()) built it) have the same state."""
    torch.manual_seed(0)
    old = RewardModel(3, 2, [8, 8])
    old_optimizer = make_adam(old.parameters(), 3e-4)
    old(torch.randn(4, 3), torch.randn(4, 2), torch.randn(4, 3)).sum().backward()
    old_optimizer.step()
    new = RewardModel(3, 2, [8, 8])
    new_optimizer = make_adam(new.parameter_groups(3e-4), 3e-4)
    new.load_state_dict(old.state_dict())  # strict: no key missing or left over
    new_optimizer.load_state_dict(old_optimizer.state_dict())
    assert "action_cost_rho" not in new.state_dict() and float(new.action_cost()) == 0.0
    assert torch.equal(new_optimizer.state_dict()["state"][0]["exp_avg"], old_optimizer.state_dict()["state"][0]["exp_avg"])


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory, poor_hopper_demos):
    """Every SMOKE run, as many at a time as there are cores: {name: (process, run folder)}. The demo file and
    the output folder are given as paths relative to the scripts' folder, where they run."""
    out = tmp_path_factory.mktemp("smoke")
    commands = []
    for name, flags in SMOKE.items():
        common = ["--env", "Hopper-v5", "--demos", os.path.relpath(poor_hopper_demos, HERE), "--num-demos", "1",
                  "--output-dir", os.path.relpath(out, HERE), "--run-name", name, "--hidden", "32", "32",
                  "--threads", "1", "--eval-episodes", "1"]
        commands.append(("bc.py", *common, *flags) if name == "bc" else
                        ("sail.py", *common, "--total-timesteps", "600", "--learning-starts", "400",
                         "--eval-freq", "200", "--disc-freq", "200", "--disc-hidden", "32", "32", *flags))
    procs = run_scripts(*commands, at_once=max(2, os.cpu_count() or 2))
    return {name: (proc, out / name) for name, proc in zip(SMOKE, procs)}


def test_on_policy_disc_from_the_first_promotion(smoke_runs, capsys):
    """--disc-negatives recent-after-promotion (the default): the whole-R_B D of the paper's SAIL while R_E
    holds only the teacher, the on-policy D once an own episode has joined it (here before learning starts)."""
    def learning(name):
        proc, run_dir = smoke_runs[name]
        assert proc.returncode == 0, proc.stderr[-3000:]
        return [{k: v for k, v in r.items() if k not in ("time", "steps_per_second")} for r in read_csv(run_dir)]
    promoted = learning("sail")
    assert int(promoted[0]["promotions"]) > 0
    assert promoted == learning("recent-negatives")
    assert learning("recent-after-promotion-no-adaptation") == learning("no-adaptation")
    assert learning("no-adaptation") != learning("recent-negatives")
    # the flags that --disc-negatives merged are gone: one line
    for argv in (["--no-on-policy-disc"], ["--on-policy-from", "promotion"], ["--disc-negatives", "promotion"]):
        proc = main_in_process(sail.main, argv, capsys)
        assert_one_line_error(proc)
        assert proc.returncode == 2 and argv[0] in proc.stderr


@pytest.mark.parametrize("name", sorted(SMOKE))
def test_smoke_run_of_each_preset_and_ablation(name, smoke_runs):
    proc, run_dir = smoke_runs[name]
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = read_csv(run_dir)
    assert list(rows[0]) == PROGRESS_COLUMNS  # the actor's evaluation only: no target-actor columns
    assert all(np.isfinite(float(r["eval_return"])) for r in rows)
    assert all(1 <= float(r["eval_length"]) < 1000 for r in rows)  # an untrained hopper falls
    model = torch.load(run_dir / "model.pt", weights_only=True)  # every run writes it at its end
    assert set(model["actor"]) and model["env"] == "Hopper-v5"
    config = json.load(open(run_dir / "config.json"))
    # what the run is and the code that ran it, and no folder of this machine
    text = (run_dir / "config.json").read_text()
    assert HERE not in text and not {"given", "output_dir", "resume"} & set(config)
    assert not [word for value in config.values() if isinstance(value, str) for word in value.split()
                if os.path.isabs(word)], config
    assert re.fullmatch(r"[0-9a-f]{7,40}(-dirty)?", config["commit"])
    if name == "bc":
        assert "bc.py" in config["command"] and config["algo"] == "bc" and config["method"] == "BC"
        assert [int(r["updates"]) for r in rows] == [100, 200, 300]
        return
    # the preset's name, and the learner flags given by hand (not those of how the run is set up)
    preset = {"sail-paper": "SAIL-paper", "dac": "DAC", "td3": "TD3 (sparse)", "ircr": "IRCR"}.get(name, "SAIL")
    if name == "rrd":  # --method NAME
        assert config["method"] == "RRD (K 16)"
    else:
        assert config["method"].startswith(preset + " (--") and "--learning-starts 400" in config["method"]
        assert not any(flag in config["method"] for flag in ("--kernels", "--seed", "--output-dir", "--demos"))
    assert ("--fixed-alpha" in config["method"]) == (name == "fixed-alpha")
    assert ("--alpha 0" in config["method"]) == (name == "no-lfd")
    assert "sail.py" in config["command"] and config["total_timesteps"] == 600
    assert config["kernels_chosen"] in ("torch", "onednn"), config  # what "auto" chose: speed means little without
    assert [int(r["global_step"]) for r in rows] == [200, 400, 600]
    assert int(rows[-1]["updates"]) == 201
    alphas = [float(r["alpha"]) for r in rows]
    if name in ("no-lfd", "dac", "td3", "ircr", "rrd"):
        assert alphas == [0.0] * 3
    if name == "fixed-alpha":
        assert alphas == [0.5] * 3
    if name in ("no-adaptation", "recent-after-promotion-no-adaptation", "dac", "td3", "ircr", "rrd"):
        assert all(int(r["promotions"]) == 0 for r in rows)
    if name not in ("sail-paper", "dac", "td3", "ircr"):  # the reward model trains with every TD3 update
        assert all(np.isfinite(float(r["decomposition_loss"])) for r in rows if int(r["global_step"]) >= 400)
    else:
        assert all(r["decomposition_loss"] == "nan" for r in rows)
    # the learned action cost c: a default of the decomposition (RRD's preset keeps the plain reward model)
    costs = [float(r["decomposition_action_cost"]) for r in rows if int(r["global_step"]) >= 400]
    if name not in ("sail-paper", "dac", "td3", "ircr", "rrd"):
        assert config["action_cost"] == ("reward" if name == "decomposition" else "reward-and-actor")
        assert all(np.isfinite(c) and c > 0 for c in costs)
    else:
        assert config["action_cost"] == "none" and all(np.isnan(c) for c in costs)
    if name in ("td3", "ircr", "rrd"):  # no discriminator trained
        assert all(r["disc_loss"] == "nan" for r in rows)
    else:
        assert 0.0 < float(rows[-1]["disc_teacher"]) < 1.0
    # by default a LayerNorm (a weight of the hidden size) after each hidden Linear of Q1 and Q2; none in the paper's
    critic = torch.load(run_dir / "checkpoint.pt", weights_only=True)["agent"]["critic"]
    assert [k for k, v in critic.items() if k.endswith("weight") and v.shape == (32,)] == \
           ([] if name in ("sail-paper", "dac", "td3", "ircr", "rrd") else
            ["q1.net.1.weight", "q1.net.4.weight", "q2.net.1.weight", "q2.net.4.weight"])
    if name == "dac":  # the agent acts with zero in the absorbing state, as the demos do
        buffer = torch.load(run_dir / "checkpoint.pt", weights_only=True)["self_buffer"]["data"]
        absorbing = buffer[0][:, -1] == 1.0
        assert absorbing.sum() > 0 and (buffer[1][absorbing] == 0).all()


def test_warm_up_waits_for_episodic_returns_where_the_critic_reward_needs_them(tmp_path):
    """Pendulum's episodes last 200 steps, longer than --learning-starts 50. The return bonus
    (IRCR, no teacher) scales by the range of returns seen, which has two ends once a second
    episode has ended, at step 400: its updates start there. TD3 on the env reward needs no
    return and starts at 50."""
    flags = ["--env", "Pendulum-v1", "--total-timesteps", "600", "--learning-starts", "50", "--eval-freq", "600",
             "--output-dir", str(tmp_path), *TINY]
    ircr, td3 = run_scripts(("sail.py", *flags, "--algo", "ircr", "--run-name", "ircr"),
                            ("sail.py", *flags, "--algo", "td3", "--run-name", "td3"))
    assert ircr.returncode == 0 and td3.returncode == 0, (ircr.stderr + td3.stderr)[-3000:]
    assert int(read_csv(tmp_path / "ircr")[-1]["updates"]) == 600 - 400 + 1
    assert int(read_csv(tmp_path / "td3")[-1]["updates"]) == 600 - 50 + 1


def test_promotion_switches_alpha_inside_the_loop(tmp_path, poor_hopper_demos):
    """The poor teacher's return is the lowest of 30 random episodes: the agent's own episodes
    beat it, are promoted, and the dynamic alpha drops from 0.5 to 0 at the first promotion. The
    small teacher capacity makes the worst episodes leave, so the threshold rises. (--learning-starts 999:
    random actions and no update but at the last step; the test is about R_E's promotions and alpha.)"""
    proc = run_script("sail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos, "--total-timesteps", "1000",
                      "--learning-starts", "999", "--eval-freq", "20", "--disc-freq", "200",
                      "--teacher-capacity", "200", "--output-dir", str(tmp_path), "--run-name", "run", *TINY)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = read_csv(tmp_path / "run")
    first = next(i for i, r in enumerate(rows) if int(r["promotions"]) > 0)
    assert all(float(r["alpha"]) == 0.5 for r in rows[:first])
    assert all(float(r["alpha"]) == 0.0 for r in rows[first:])
    assert int(rows[-1]["promotions"]) > int(rows[-1]["teacher_episodes"]) > 1  # some were evicted
    assert float(rows[-1]["teacher_threshold"]) > float(rows[0]["teacher_threshold"])


# fixed kernels: `auto` times them in each process and may choose differently in two runs
# a small R_E: promotions evict episodes within these 1000 steps, across a resume too
RESUME_FLAGS = ["--env", "Hopper-v5", "--learning-starts", "500", "--eval-freq", "250", "--disc-freq", "100",
                "--teacher-capacity", "150",
                "--seed", "3", "--kernels", "onednn" if cpu_kernels.AVAILABLE else "torch", *TINY]


@pytest.fixture(scope="module")
def straight_runs(tmp_path_factory, poor_hopper_demos):
    """Side by side: a run of 1000 steps with sail.py's defaults, never interrupted (what every interrupted
    and resumed one must equal); the same run of the paper's SAIL (no return decomposition, plain critics);
    the first run stopped at step 700, which test_resume_equals_an_uninterrupted_run resumes; and the first
    run with --teacher-keep return (R_E drops its lowest return first, the paper's rule)."""
    out = tmp_path_factory.mktemp("straight")
    flags = [*RESUME_FLAGS, "--demos", poor_hopper_demos, "--output-dir", str(out)]
    procs = run_scripts(("sail.py", *flags, "--total-timesteps", "1000", "--run-name", "a"),
                        ("sail.py", *flags, "--algo", "sail-paper", "--total-timesteps", "1000", "--run-name", "paper"),
                        ("sail.py", *flags, "--total-timesteps", "700", "--run-name", "stopped"),
                        ("sail.py", *flags, "--total-timesteps", "1000", "--teacher-keep", "return",
                         "--run-name", "return"))
    for proc in procs:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return {"straight": out / "a", "paper": out / "paper", "stopped": out / "stopped", "return": out / "return"}


@pytest.fixture(scope="module")
def straight_run(straight_runs):
    return straight_runs["straight"]


@pytest.fixture(scope="module")
def straight_paper_run(straight_runs):
    return straight_runs["paper"]


def learning_rows(run_dir):
    """progress.csv's rows without speed and time, the columns in which two runs of one command differ."""
    return [{k: v for k, v in row.items() if k not in ("steps_per_second", "time")} for row in read_csv(run_dir)]


def assert_same_run(run_a, run_b):
    rows_a, rows_b = learning_rows(run_a), learning_rows(run_b)
    assert len(rows_a) == 4 and rows_a == rows_b
    model_a = torch.load(run_a / "model.pt", weights_only=True)
    model_b = torch.load(run_b / "model.pt", weights_only=True)
    for key in ("actor", "critic", "discriminator"):
        for name, value in model_a[key].items():
            torch.testing.assert_close(value, model_b[key][name], rtol=0, atol=0)


def test_resume_equals_an_uninterrupted_run(straight_runs):
    """With sail.py's defaults: D, the agent, the reward model of the return decomposition with its learned
    action cost, their optimizers and the buffer's episode bounds (stopped mid-episode) are in the checkpoint."""
    # the run stopped just after D's training at step 700: the evaluation at 750 logs that training's losses
    stopped = straight_runs["stopped"]
    # same thread count: with another one, MKL and oneDNN may sum in another order (seen on Intel)
    resumed = run_script("sail.py", "--resume", str(stopped), "--total-timesteps", "1000")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(straight_runs["straight"], stopped)
    assert all(np.isfinite(float(r["decomposition_loss"])) and np.isfinite(float(r["decomposition_action_cost"]))
               for r in read_csv(stopped)[2:])  # c logged


def test_decomposition_probe_reports_the_learned_reward_and_its_action_cost(straight_run, straight_paper_run):
    probe = os.path.join("results", "rrd_probe.py")
    proc, without, bad = run_scripts((probe, str(straight_run), "--noise", "0", "0.1", "--refit", "8",
                                      "--refit-steps", "20", "--refit-hidden", "16"),
                                     (probe, str(straight_paper_run)),
                                     (probe, str(straight_run), "--refit", "0"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    scaling = [f"actions x {k}" for k in (0.0, 0.5, 1.0, 1.5)]
    heads = [line.split(":")[0] for line in lines]
    assert heads[:2] == ["noise 0.0", "noise 0.1"] and heads[3:7] == scaling and heads[8:12] == scaling
    assert re.match(r"learned action cost c = [0-9.e-]+ per unit of squared action norm", lines[2])
    assert re.match(r"refit with subsets of 8 steps, hidden \[16\], 20 minibatches \(mean loss of the last 20: \S+, "
                    r"c = [0-9.e-]+\)", lines[7])
    for block in (lines[3:7], lines[8:12]):  # the run's reward model on a played episode; the refit one on R_B
        changes = [re.search(r"mean r (\S+) a step, the env's control cost (\S+) a step$", line).groups()
                   for line in block]
        assert [float(c) for c in changes[2]] == [0.0, 0.0]  # the actions as played
        cost = [float(c[1]) for c in changes]
        assert cost[0] < cost[1] < 0 <= cost[3]  # the control cost grows with the actions (to their bounds)
    assert "on R_B's last 1000 transitions" in lines[7]  # all of the 1000-step run's
    # the refit model's per-step correlation with the dense reward on each episode played above
    fits = re.fullmatch(r"per-step correlation with the dense reward and slope: "
                        r"noise 0.0 (\S+) (\S+), noise 0.1 (\S+) (\S+)", lines[12])
    assert len(lines) == 13 and fits and all(-1 <= float(r) <= 1 for r in fits.groups()[::2])
    # what the dense reward would pay in RRD's loss at the refit's K and the run's: less for more steps, and
    # nothing where the subset is the whole episode
    terms = [re.search(r": (\d+) steps, .*, per-step correlation \S+, slope -?[0-9.]+; the dense reward's variance "
                       r"term K = 8 (\S+), K = (\d+) (\S+)$", line) for line in lines[:2]]
    assert all(terms) and all(int(t[3]) == sail.parse_args([]).decomposition_subset for t in terms)  # the run's K
    assert all(float(t[2]) > float(t[4]) >= 0 for t in terms)
    assert all((float(t[4]) == 0) == (int(t[1]) <= int(t[3])) for t in terms)
    assert without.returncode == 2 and "without --return-decomposition" in without.stderr
    assert bad.returncode == 2 and "--refit sizes must be" in bad.stderr


def test_a_run_killed_at_any_moment_resumes_to_the_uninterrupted_result(tmp_path, poor_hopper_demos, straight_run):
    """SIGKILL leaves no chance to save: the run must go on from its last periodic checkpoint,
    whether it was killed between checkpoints or while writing one (atomic writes)."""
    import time
    run_dir = tmp_path / "k"
    command = ["sail.py", *RESUME_FLAGS, "--demos", poor_hopper_demos, "--total-timesteps", "1000",
               "--output-dir", str(tmp_path), "--run-name", "k"]  # a checkpoint with each evaluation
    kills = 0
    for moment in ("after the first checkpoint", "while a checkpoint is written", "later"):
        proc = start_script(command, os.devnull, os.devnull)  # kill() sends SIGKILL
        # a checkpoint's write lasts milliseconds: if the polling misses every one for 5 s, kill anyway
        deadline = time.time() + (5 if moment == "while a checkpoint is written" and kills else 120)
        checkpoint = run_dir / "checkpoint.pt"
        start_mtime = checkpoint.stat().st_mtime_ns if checkpoint.exists() else 0
        while time.time() < deadline and proc.is_alive():
            if moment == "while a checkpoint is written":
                if any(p.name.startswith("checkpoint.pt.tmp") for p in run_dir.iterdir()):
                    break
            elif checkpoint.exists() and checkpoint.stat().st_mtime_ns != start_mtime:
                if moment == "later":
                    time.sleep(1.0)
                break
            time.sleep(0.001)
        if proc.is_alive():
            proc.kill()
            kills += 1
        proc.join()
        command = ["sail.py", "--resume", str(run_dir)]
    assert kills >= 2  # the run was really cut short (it needs far longer than the waits above)
    finished = run_script(*command)
    assert finished.returncode == 0, finished.stderr[-3000:]
    assert int(read_csv(run_dir)[-1]["global_step"]) == 1000
    assert_same_run(straight_run, run_dir)


def test_early_end_probe_on_ant_shows_the_reward_by_steps_to_a_flip_and_the_resting_actor(tmp_path, straight_run):
    """On an Ant-v5 run the probe ends with the critic's reward parts and Q (at the actor's and at the
    zero action) by steps to the first step upside down; --rest-when-upside-down plays the actor that
    rests once upside down, and is refused on other envs with one line."""
    proc = run_script("sail.py", "--env", "Ant-v5", "--total-timesteps", "1200", "--learning-starts", "1000",
                      "--eval-freq", "1200", "--disc-freq", "100", "--seed", "1",
                      "--action-cost", "reward-and-actor", *TINY, "--output-dir", str(tmp_path),
                      "--run-name", "ant")
    assert proc.returncode == 0, proc.stderr[-3000:]
    probe = os.path.join("results", "early_ends.py")
    played, resting, refused = run_scripts((probe, str(tmp_path / "ant"), "--episodes", "1"),
                                           (probe, str(tmp_path / "ant"), "--episodes", "1", "--rest-when-upside-down"),
                                           (probe, str(straight_run), "--rest-when-upside-down"))
    assert played.returncode == 0 and resting.returncode == 0, played.stderr[-3000:] + resting.stderr[-3000:]
    assert any(line.startswith("Ant-v5, actor: mean return") for line in played.stdout.splitlines())
    assert any(line.startswith("Ant-v5, actor (the zero action once upside down): mean return")
               for line in resting.stdout.splitlines())
    lines = played.stdout.splitlines()
    start = lines.index(next(line for line in lines if line.startswith("the critic's reward and min(Q1, Q2)")))
    groups = lines[start + 1:]
    assert [line.split(":")[0].strip() for line in groups] == [
        "episodes never upside down", "over 100 steps before", "31-100 steps before", "11-30 steps before",
        "1-10 steps before", "upside down", "upright again after a flip"]
    never = groups[0]  # 1200 random and barely trained steps: some finished episodes, each part of the reward
    assert re.match(r"  episodes never upside down: \d+ transitions, D's reward -?\d+\.\d{3}, return bonus "
                    r"-?\d+\.\d{3}, learned reward -?\d+\.\d{3}, Q -?\d+\.\d{2} \(at the zero action "
                    r"-?\d+\.\d{2}\), squared action norm \d+\.\d{2}$", never), never
    assert refused.returncode == 2 and refused.stderr.strip().splitlines()[-1].endswith(
        "--rest-when-upside-down is for Ant-v5 runs")


def test_actor_drift_probe_measures_the_actor_against_its_target_on_the_targets_states(tmp_path, straight_run):
    """results/actor_drift.py: the target actor's episodes, then on their states the actor's distance from the
    target (> 0 once the actor has stepped: the target moves by tau of the way), the critic at both actions,
    Adam's |m| / sqrt(v), the critic's own policy's episodes and the critic's Q against the reward that followed
    along the actor's; a folder that is not a run is one error line."""
    probe = os.path.join("results", "actor_drift.py")
    proc, missing = run_scripts((probe, str(straight_run), "--episodes", "2", "--critic-search", "2",
                                 "--critic-check", "2"), (probe, str(tmp_path)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert re.match(r"Hopper-v5 at step 1000: the target actor's episodes, returns -?\d+, -?\d+; lengths \d+, \d+$",
                    lines[0]), lines[0]
    drift = re.match(r"on their (\d+) states: mean \|actor - target\| per action entry (\d\.\d{3}) \(half ranges\); "
                     r"at the bounds: actor \d\.\d{3}, target \d\.\d{3}$", lines[1])
    lengths = [int(n) for n in lines[0].split("lengths ")[1].split(", ")]
    assert drift and int(drift[1]) == sum(lengths) and 0 < float(drift[2]) < 2, lines[1]
    assert re.match(r"critic's min\(Q1, Q2\): at the actor's actions -?\d+\.\d, at the target's -?\d+\.\d, "
                    r"mean \|difference\| \d+\.\d\d$", lines[2]), lines[2]
    assert re.match(r"the actor's episode: return -?\d+, \d+ steps, (terminated|truncated); min\(Q1, Q2\) at its "
                    r"actions, step 1: -?\d+\.\d(, step \d+: -?\d+\.\d)*; the observation at its last step, first "
                    r"entries -?\d\.\d{3}, -?\d\.\d{3}$", lines[3]), lines[3]
    assert [line.split(":")[0] for line in lines[4:6]] == ["actor's Adam", "critic's Adam"]
    search = re.match(r"the critic's own policy \(its best of the actor's action and 64 perturbed ones\): returns "
                      r"-?\d+, -?\d+; lengths (\d+), (\d+); (\d) of 2 ended early$", lines[6])
    assert search and int(search[3]) <= 2 and min(int(search[1]), int(search[2])) >= 1, lines[6:]
    check = re.match(r"the actor's 2 episodes \(returns -?\d+, -?\d+; ([0-2]) ended early\): over their first 50 "
                     r"steps the critic's min\(Q1, Q2\) (-?\d+\.\d), the discounted reward that followed (-?\d+\.\d)",
                     lines[7])
    assert check and len(lines) == 9 and float(check[3]) != 0, lines[7:]
    each = re.match(r"  per episode, over its first 50 steps: min\(Q1, Q2\) (-?\d+\.\d), (-?\d+\.\d); the discounted "
                    r"reward that followed (-?\d+\.\d), (-?\d+\.\d)$", lines[8])
    assert each and abs((float(each[1]) + float(each[2])) / 2 - float(check[2])) < 0.11, lines[8]
    assert missing.returncode == 2 and "has no config.json" in missing.stderr.strip().splitlines()[-1]


def test_exploration_noise_is_white_with_the_exploration_noise_std(tmp_path):
    """A run whose actor no update moves (--policy-delay past its end), so each action R_B holds once learning
    starts is that actor's plus the noise, clipped to the bounds: Gaussian noise of std 0.1 (Hopper-v5's half
    range is 1), uncorrelated from step to step."""
    flags = ["--env", "Hopper-v5", "--policy-delay", "10000", "--learning-starts", "500", "--total-timesteps", "800",
             "--eval-freq", "800", "--seed", "4", "--output-dir", str(tmp_path), *TINY]
    proc, = run_scripts(("sail.py", *flags, "--run-name", "white"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    saved = load_checkpoint(tmp_path / "white" / "checkpoint.pt")
    obs, actions = (saved["self_buffer"]["data"][i][600:800] for i in (0, 1))
    actor = Actor(obs.shape[1], actions.shape[1], [32, 32], -np.ones(3), np.ones(3))
    actor.load_state_dict(saved["agent"]["actor"])
    policy = actor(obs).detach()
    noise = actions - policy
    unclipped = ((policy + noise).abs() < 0.999).all(dim=1)
    white = noise[unclipped]
    assert unclipped.sum() > 150 and 0.08 < white.std() < 0.12, (unclipped.sum(), white.std())
    lag1 = (white[1:] * white[:-1]).mean() / white.var()  # neighbours in R_B, mostly neighbouring steps
    assert abs(lag1) < 0.2, lag1


def test_terminal_refit_fits_the_critic_to_r_b_s_terminal_transitions_when_they_fill_its_batches(tmp_path,
                                                                                                 straight_run):
    """results/terminal_refit.py: the actor's episode and R_B's terminal transitions, then two refits of the critic;
    with every batch made of terminal transitions (--share 1) Q on them moves towards their reward, which is the
    whole target there; a folder that is not a run is one error line."""
    probe = os.path.join("results", "terminal_refit.py")
    proc, missing = run_scripts((probe, str(straight_run), "--share", "1", "--updates", "40"), (probe, str(tmp_path)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert re.match(r"Hopper-v5 at step 1000: the actor's episode, return -?\d+, \d+ steps, (terminated|truncated); "
                    r"R_B's terminal transitions: \d+ of its last 100000, [1-9]\d* in all$", lines[0]), lines[0]
    assert [line.split(":")[0] for line in lines[1:]] == (["checkpoint"] + [f"share 0, {i} updates" for i in
                                                                          (10, 20, 30, 40)]
                                                          + [f"share 1, {i} updates" for i in (10, 20, 30, 40)])
    gap = [abs(float(q) - float(r)) for q, r in
           (re.search(r"R_B's terminals \(all\): Q (-?\d+\.\d), reward (-?\d+\.\d\d)$", lines[i]).groups()
            for i in (1, -1))]
    assert gap[1] < gap[0], lines
    assert missing.returncode == 2 and "has no config.json" in missing.stderr.strip().splitlines()[-1]


def test_early_end_probe_reports_each_episode_of_a_run(tmp_path, straight_run):
    probe = os.path.join("results", "early_ends.py")
    proc, missing, resting, timeless, noisy, bad_noise = run_scripts(
        (probe, str(straight_run), "--episodes", "3"), (probe, str(tmp_path)),
        (probe, str(straight_run), "--episodes", "2", "--zero-start", "1000"),
        (probe, str(straight_run), "--episodes", "1", "--time-left", "0.0"),
        (probe, str(straight_run), "--episodes", "1", "--noise", "0.5"),
        (probe, str(straight_run), "--noise", "0.1", "--target"))
    assert proc.returncode == 0 and resting.returncode == 0, proc.stderr[-3000:] + resting.stderr[-3000:]
    # --noise X: the actor as training plays it, so the same first episode goes otherwise; not with --target
    assert noisy.returncode == 0 and "Hopper-v5, actor (with exploration noise 0.5): mean return" in noisy.stdout
    assert bad_noise.returncode == 2 and "--noise takes X >= 0" in bad_noise.stderr.strip().splitlines()[-1]
    # --time-left X: the actor sees 1 - t/T as X; the same first episode (env seed 1000) then goes otherwise
    assert timeless.returncode == 0, timeless.stderr[-3000:]
    assert "Hopper-v5, actor (seeing the time feature as 0.0): mean return" in timeless.stdout
    first = [next(line for line in out.stdout.splitlines() if line.startswith("episode 1:"))
             for out in (proc, timeless, noisy)]
    assert first[0] != first[1] and first[0] != first[2], first
    # --zero-start N: the zero action for each episode's first N steps, here for all of them
    assert "Hopper-v5, actor (the zero action for the first 1000 steps): mean return" in resting.stdout
    assert "squared action norm per step: actor 0.000 (0.000 in the first 20 steps)" in resting.stdout
    lines = proc.stdout.splitlines()
    episodes = [line for line in lines if line.startswith("episode ")]
    assert len(episodes) == 3 and all("ended early" in line for line in episodes)  # a barely trained hopper falls
    assert all(re.search(r"\(forward reward -?\d+, control cost \d+\)", line) for line in episodes)
    summary = lines.index(next(line for line in lines if line.startswith("Hopper-v5, actor:")))
    assert "3 ended early" in lines[summary] and lines[summary + 1].startswith("teacher (1 episodes): first entry")
    assert re.match(r"squared action norm per step: actor \d+\.\d{3} \(\d+\.\d{3} in the first 20 steps\)",
                    lines[summary + 2])  # and the control cost it makes
    assert "control cost weight 0.001:" in lines[summary + 2]  # Hopper-v5's
    # the teacher's and R_E's squared action norms, over whole episodes and (in brackets) their first 20 steps
    with np.load(json.load(open(straight_run / "config.json"))["demos"]) as demos:
        teacher = (demos["actions"][:demos["episode_lengths"][0]] ** 2).sum(-1)
    kept = [data[1] ** 2 for _, data in torch.load(straight_run / "checkpoint.pt")["teacher_buffer"]["episodes"]]
    assert (f"teacher {teacher.mean():.3f} ({teacher[:20].mean():.3f}), R_E's {len(kept)} episodes "
            f"{np.mean([a.sum(-1).mean() for a in kept]):.3f} ") in lines[summary + 2]
    training = lines[summary + 4]  # R_B's episodes: the straight run's 1000 steps, nearly all falls
    assert lines[summary + 3].startswith("training episodes (R_B") and training.startswith("  0-50000: ")
    falls = int(training.split(" ended early")[0].split(", ")[-1])
    assert falls >= 10
    # the critic by steps to a termination: one terminal step per fall, and no episode ran to the limit
    assert lines[summary + 5].startswith("the critic's min(Q1, Q2) at R_B's actions (last 1000 transitions)")
    groups = lines[summary + 6:]
    assert [line.split(":")[0].strip() for line in groups] == [
        "0 (the terminal step)", "1-3", "4-10", "11-30", "31-100", "episodes that ran to the limit"]
    assert groups[0].startswith(f"  0 (the terminal step): {falls} transitions, mean over {falls}: Q ")
    assert groups[-1] == "  episodes that ran to the limit: none"
    assert missing.returncode == 2 and "has no config.json" in missing.stderr


def test_results_scripts_refuse_an_unreadable_run_folder_in_one_line(tmp_path):
    """Each results script that opens a RUN_DIR: a broken config.json, then a good one beside a checkpoint.pt
    that is not one, is one error line naming the file and exit 2, before any work."""
    broken, bad_checkpoint = tmp_path / "broken", tmp_path / "bad_checkpoint"
    good = open(os.path.join(HERE, "results", "pareto-teacher", "Hopper-v5__sail-dan-cost-actor__9", "config.json")).read()
    for folder, config in ((broken, "{"), (bad_checkpoint, good)):
        folder.mkdir()
        (folder / "config.json").write_text(config)
        (folder / "checkpoint.pt").write_text("not a checkpoint")
    scripts = [os.path.join("results", f"{name}.py") for name in ("probe", "early_ends", "rrd_probe", "keep_replay",
                                                                   "actor_drift", "terminal_refit")]
    procs = run_scripts(*[(script, str(folder)) for folder in (broken, bad_checkpoint) for script in scripts])
    for proc, file in zip(procs, ["config.json"] * len(scripts) + ["checkpoint.pt"] * len(scripts)):
        error = proc.stderr.strip().splitlines()[-1]
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert re.match(r"\w+\.py: error: (cannot read )?\S+/" + re.escape(file) + r"\b", error), error


def test_keep_replay_finds_where_the_two_teacher_keep_rules_part(straight_runs):
    """The replay of both R_E rules on a run's own episodes reproduces its checkpoint's R_E (after promotions
    that evicted episodes), names the same parting step from either run of a pair, and up to that step the
    two runs are one run. (After it they may still be: R_E is not sampled before --learning-starts.)"""
    replay = os.path.join("results", "keep_replay.py")
    by_pareto, by_return = run_scripts((replay, str(straight_runs["straight"])), (replay, str(straight_runs["return"])))
    parted = []
    for proc in (by_return, by_pareto):
        assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
        lines = proc.stdout.splitlines()
        assert re.match(r"replayed with its own rule: \d+ promotions, R_E at the end matches the checkpoint", lines[1])
        parted.append(re.fullmatch(r"the two rules part after the episode that ends at step (\d+)", lines[2]))
    # the poor teacher's 11-step episode, random episodes of many lengths and a 150-step R_E: the rules part
    assert parted[0] and parted[1] and parted[0][1] == parted[1][1]
    step = int(parted[0][1])
    before = [(a, b) for a, b in zip(learning_rows(straight_runs["straight"]), learning_rows(straight_runs["return"]))
              if int(a["global_step"]) <= step]
    assert before and all(a == b for a, b in before)


def test_checkpoint_probe_reports_q_slope_and_d(straight_paper_run, straight_run):
    probe = os.path.join("results", "probe.py")
    proc, decomposition = run_scripts((probe, str(straight_paper_run)), (probe, str(straight_run)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert decomposition.returncode == 0, decomposition.stderr[-3000:]
    learned = [line for line in decomposition.stdout.splitlines()
               if "transitions, D's reward" in line and "steps to the end" not in line]
    parsed = [re.search(r"D's reward (-?\d+\.\d+), learned reward (-?\d+\.\d+), critic's reward (-?\d+\.\d+), "
                        r"Q -?\d+\.\d, squared action norm", line) for line in learned]
    assert learned and all(parsed)
    # the critic's reward is D's plus the learned one over one unit, the same in every bin
    per_unit = [(float(m[3]) - float(m[1])) / float(m[2]) for m in parsed if abs(float(m[2])) >= 0.1]
    assert per_unit and all(u > 0 for u in per_unit) and max(per_unit) == pytest.approx(min(per_unit), rel=0.1)
    q_line, *d_lines = proc.stdout.splitlines()
    d_lines, bins, teacher_lines = d_lines[:9], d_lines[9:18], d_lines[18:]
    mean_q, slope, ratio = map(float, re.search(r"mean \|Q\| (\S+), mean slope per action dimension (\S+), "
                                                r"their ratio (\S+)$", q_line).groups())
    assert mean_q > 0 and slope > 0
    assert ratio == pytest.approx(slope / mean_q, rel=0.05)  # of the printed numbers, rounded
    assert len(d_lines) == 9 and all(0 <= float(line.rsplit(": ", 1)[1]) <= 1 for line in d_lines)
    assert [line.split(": ")[0] for line in d_lines[4:]] == [f"D on the teacher's states, actions x {k}"
                                                           for k in (0.0, 0.5, 1.0, 1.5, 2.0)]
    # the rewards by bins of the torso's height: every transition of the 1000-step R_B in one of 8 bins
    assert bins[0] == "R_B's last 1000 transitions by observation 0:" and len(bins) == 9
    counts = [int(m.group(1)) for m in (re.search(r": (\d+) transitions, D's reward", line) for line in bins[1:]) if m]
    assert sum(counts) == 1000 and not any("learned reward" in line for line in bins)  # a run without the decomposition
    # R_E: the demo episode and the promoted ones, the lowest return first: the run's last threshold
    header, *kept = teacher_lines
    count = int(re.fullmatch(r"R_E: (\d+) episodes \(return, steps, mean of observation 8\):", header).group(1))
    kept, by_end = kept[:count], kept[count:]
    returns = [float(line.split(",")[0]) for line in kept]
    assert returns == sorted(returns)
    assert returns[0] == pytest.approx(float(read_csv(straight_paper_run)[-1]["teacher_threshold"]), abs=0.05)
    # then R_E by steps to the end of each episode: every kept transition counted once, in the fallen or the cut
    assert by_end[0] == "R_E by steps to its episode's end:"
    counted = [re.fullmatch(r"  (fell|ran to the time limit), \d+(-\d+| or more) steps to the end: (\d+) transitions, "
                            r"D's reward \d+\.\d\d, Q -?\d+\.\d, observation 8 -?\d+\.\d\d", line) for line in by_end[1:]]
    assert by_end[-1] == "  ran to the time limit: no episode"  # the straight runs' episodes are short
    assert all(counted[:-1]), by_end
    assert sum(int(m[3]) for m in counted[:-1]) == sum(int(line.split(", ")[1]) for line in kept)


def test_checkpoints_are_read_onto_the_cpu_whatever_the_run_device(tmp_path, monkeypatch):
    """Buffers (numpy views) and RNG states only exist on the CPU, so a checkpoint is always read
    with map_location="cpu" and each part's load_state_dict moves its own tensors: reading it onto
    cuda made `--resume` of a `--device cuda` run fail (found on a GPU, where --resume now works
    cuda->cuda, cuda->cpu and cpu->cuda)."""
    import plumbing
    rng = np.random.default_rng(0)
    net = torch.nn.Linear(3, 2)
    optimizer = torch.optim.Adam(net.parameters())
    net(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    path = tmp_path / "checkpoint.pt"
    plumbing.save_checkpoint(path, {"net": net, "optimizer": optimizer, "rngs": plumbing.RNGs(rng)},
                             obs=np.arange(3, dtype=np.float32))
    map_locations, torch_load = [], torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: map_locations.append(k.get("map_location")) or torch_load(*a, **k))
    net2 = torch.nn.Linear(3, 2)
    optimizer2 = torch.optim.Adam(net2.parameters())
    expected_state = np.random.default_rng(0).bit_generator.state
    saved = plumbing.load_checkpoint(path, {"net": net2, "optimizer": optimizer2, "rngs": plumbing.RNGs(np.random.default_rng(5))})
    assert map_locations == ["cpu"]
    assert isinstance(saved["obs"], np.ndarray) and saved["obs"].tolist() == [0, 1, 2]
    assert torch.equal(net2.weight, net.weight) and optimizer2.state_dict()["state"][0]["step"] == 1
    assert saved["rngs"]["numpy"] == expected_state


def test_resume_needs_neither_the_demo_file_nor_the_device_the_run_was_made_with(tmp_path, straight_run, capsys,
                                                                                monkeypatch):
    """R_E comes from the checkpoint, so a resumed run does not read the demo file again (it may have moved);
    a run made on a GPU, resumed where there is none, is one line that names the way out."""
    import shutil
    import sail
    run = shutil.copytree(straight_run, tmp_path / "run")
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps(config | {"demos": str(tmp_path / "moved.npz")}))
    proc = main_in_process(sail.main, ["--resume", str(run)], capsys)  # got past the demos, to the finished run
    assert_one_line_error(proc)
    assert "has finished" in proc.stderr
    (run / "config.json").write_text(json.dumps(config | {"device": "cuda"}))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    proc = main_in_process(sail.main, ["--resume", str(run), "--total-timesteps", "5000"], capsys)
    assert_one_line_error(proc)
    assert "no CUDA device" in proc.stderr and "--device cpu" in proc.stderr


def test_evaluate_runs_the_saved_actor_from_model_or_checkpoint(tmp_path, straight_run, capsys):
    import shutil
    run = shutil.copytree(straight_run, tmp_path / "run")  # with model.pt (every run's) and checkpoint.pt
    noisy = ("evaluate.py", str(run), "--episodes", "3", "--seed", "7", "--noise", "0.3")
    from_model, noisy_a, noisy_b, noise_alone = run_scripts(
        ("evaluate.py", str(run), "--episodes", "3", "--seed", "7"), noisy, noisy,
        ("sail.py", "--env", "Hopper-v5", "--eval-noise", "0.1"))
    # with noise: the actor as it acts in training, reproducible from --seed, and not the deterministic episodes
    assert noisy_a.returncode == 0 and noisy_a.stdout == noisy_b.stdout, noisy_a.stderr[-3000:]
    assert "exploration noise 0.3" in noisy_a.stdout and noisy_a.stdout.splitlines()[:3] != from_model.stdout.splitlines()[:3]
    assert_one_line_error(noise_alone)  # evaluating is evaluate.py's: sail.py has no --eval-noise
    os.remove(run / "model.pt")  # the final checkpoint holds the same actor
    reader_gone = subprocess.Popen([sys.executable, "evaluate.py", str(run)], cwd=HERE,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    reader_gone.stdout.close()  # as `| head -1` does after its line
    from_checkpoint = run_script("evaluate.py", str(run), "--episodes", "3", "--seed", "7")
    assert reader_gone.wait(timeout=120) == 1 and reader_gone.stderr.read() == ""
    for proc in (from_model, from_checkpoint):
        assert proc.returncode == 0, proc.stderr[-3000:]
    episodes = from_model.stdout.splitlines()[:3]
    assert [line.split(":")[0] for line in episodes] == ["episode 1", "episode 2", "episode 3"]
    assert from_checkpoint.stdout.splitlines()[:3] == episodes
    assert "checkpoint.pt: mean return" in from_checkpoint.stdout.splitlines()[3]
    config = json.load(open(run / "config.json"))
    json.dump(config | {"hidden": [64, 64]}, open(run / "config.json", "w"))  # not the saved sizes
    assert_one_line_error(run_script("evaluate.py", str(run)))
    os.remove(run / "checkpoint.pt")
    assert_one_line_error(run_script("evaluate.py", str(run)))


def test_evaluate_renders_a_video_headless(tmp_path, straight_run):
    import imageio.v3 as iio
    video = tmp_path / "hopper.gif"
    proc, *bad = run_scripts(("evaluate.py", str(straight_run), "--episodes", "2", "--video", str(video)),
                             ("evaluate.py", str(straight_run), "--video", str(tmp_path / "x.avi")),
                             ("sail.py", "--env", "Hopper-v5", "--video", str(video)))  # evaluate.py's flag
    assert proc.returncode == 0, proc.stderr[-3000:]
    lengths = [int(line.split("length ")[1]) for line in proc.stdout.splitlines() if line.startswith("episode")]
    from evaluate import gif_frames
    stride, delay = gif_frames(125)  # Hopper's render_fps
    assert (stride, delay) == (5, 40)  # real time, and a delay that browsers honour (>= 20 ms)
    frames = iio.imread(video)  # every 5th frame of each episode (its reset frame included), half size
    assert frames.shape == (sum(len(range(0, n + 1, stride)) for n in lengths), 240, 240, 3)
    assert iio.immeta(video, index=0)["duration"] == delay
    assert frames.std() > 1.0  # a picture, not a blank
    for proc in bad:
        assert_one_line_error(proc)
    # the camera follows the hopper (gymnasium's own free camera would let it hop out of the picture)
    import mujoco
    from evaluate import follow_the_body
    env = make_env("Hopper-v5", 0, render_mode="rgb_array")
    follow_the_body(env)
    renderer = env.unwrapped.mujoco_renderer
    assert renderer.camera_id is None and renderer.default_cam_config["type"] == mujoco.mjtCamera.mjCAMERA_TRACKING


def main_in_process(main, argv, capsys):
    """Calls a script's main(argv) here, as `python script.py ARGV` would, without a new
    interpreter importing torch again: a CompletedProcess with the exit code and stderr."""
    threads = torch.get_num_threads()
    try:
        code = main(list(argv))
    except SystemExit as e:  # argparse's errors
        code = e.code
    finally:
        torch.set_num_threads(threads)
    return subprocess.CompletedProcess(argv, code, *capsys.readouterr())


def test_bad_input_is_one_line_before_training(tmp_path, poor_hopper_demos, capsys):
    import sail
    out = ["--output-dir", str(tmp_path / "runs")]
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for argv in (["--env", "NoSuchEnv-v5", *out],
                 ["--env", "Walker2d-v5", "--demos", poor_hopper_demos, *out],
                 ["--env", "Hopper-v5", "--demos", poor_hopper_demos, "--num-demos", "5", *out],
                 ["--env", "Hopper-v5", "--demos", str(tmp_path / "none.npz"), *out],
                 ["--total-timesteps", "-5", *out],
                 ["--alpha", "1.5", *out],
                 ["--reward", "env", *out],  # env reward with teacher batches
                 ["--resume", str(tmp_path / "nothing")],
                 ["--env", "nosuchmodule:Foo-v0", *out],
                 ["--env", "Hopper-v5", "--demos", str(tmp_path), *out],
                 ["--hidden", "0", *out],
                 ["--eval-freq", "5000", "--total-timesteps", "1000", "--learning-starts", "100", *out],
                 ["--return-decomposition", "0", "--action-cost", "reward", *out],
                 ["--env", "Hopper-v5", "--demos", poor_hopper_demos, "--num-demos", "4", "--teacher-capacity", "20",
                  *out],  # R_E would drop demos as it loads them
                 ["--absorbing", *out], ["--algo", "td3", "--absorbing", *out],  # a reward repeated forever
                 ["--seed", "-1", *out], ["--seed", str(2**32), *out],  # numpy, gymnasium or torch would refuse it
                 ["--lr", "inf", *out],  # would only show up as a diverged loss
                 ["--threads", "100000", *out],  # torch's thread pools would fail to start: a crash
                 ["--env", "Hopper-v5", "--demos", poor_hopper_demos, "--kernels", "torch",  # (auto: timed first)
                  "--output-dir", str(blocker / "runs")]):
        assert_one_line_error(main_in_process(sail.main, argv, capsys))
    # the flags of the experiments that left the code, and the flags merged into others
    for removed in (["--noise-beta", "1"], ["--n-step", "3"], ["--bc-weight", "1"],
                    ["--action-l2", "1"], ["--action-budget", "teacher"], ["--return-scale", "rank"],
                    ["--alpha-anneal-steps", "100"], ["--no-contact-forces"], ["--deploy", "target"], ["--no-lfd"],
                    ["--on-policy-disc"], ["--decomposition-action-cost"], ["--actor-action-cost"],
                    ["--disc-batch-size", "64"], ["--save-model"], ["--checkpoint-freq", "100"],
                    ["--evaluate", str(tmp_path)], ["--video", "x.gif"], ["--eval-noise", "0.1"], ["--utd", "2"]):
        proc = main_in_process(sail.main, [*removed, *out], capsys)
        assert_one_line_error(proc)
        assert "unrecognized arguments: " + removed[0] in proc.stderr
    assert not os.path.exists(tmp_path / "runs")  # nothing was started


def test_sail_surpasses_a_poor_teacher_and_the_no_adaptation_ablation_does_not(tmp_path):
    """The point of the paper in under a minute, with the paper's SAIL (sail.py's default return
    bonus and return decomposition learn from the episodic returns without R_E's adaptation too).

    Why this is a fair check: the task is sparse episodic through the same wrappers as MuJoCo
    (the learner only ever gets the episodic return at the end of a 100-step episode); the
    teacher is deliberately poor (a constant push of 0.2, return ~19, against ~96 for the best
    policy); both runs share every flag and seed and differ only in --no-adaptation. Imitation
    alone rewards behaving like the teacher, so the ablation ends near the teacher's return; only
    the adaptive teacher buffer, fed by the sparse episodic return, lets SAIL end far above it.
    The runs are deterministic for a seed on a given CPU. Seeds 1-3 (2026-11-21, Intel Xeon,
    oneDNN layers): SAIL ends at 96 in each; the ablation at 29, 22 and -96. Seeds 1-2 on an AMD
    EPYC (2026-11-24): SAIL at 96 from step 2000 on; the ablation at 96 from 2000 to 4000 or
    7000 steps, then ending at -7 and -96. On its way the ablation has excursions far above the
    teacher while its discriminator, smooth under the gradient penalty, still rewards actions
    beyond the teacher's: that is why the test reads the end of the run and allows the
    ablation up to twice the teacher's return.
    """
    env_id = "test_sail:PointMass-v0"
    env = make_env(env_id, seed=0, sparse=False, time_feature=False)
    episodes = [rollout(env, lambda obs: np.array([0.2], np.float32)) for _ in range(4)]
    demos = str(tmp_path / "PointMass.npz")
    save_demos(demos, episodes, env_id)
    teacher_return = episodes[0]["episodic_return"]
    common = ["sail.py", "--algo", "sail-paper", "--env", env_id, "--demos", demos, "--total-timesteps", "10000",
              "--learning-starts", "1000", "--eval-freq", "1000", "--eval-episodes", "3", "--disc-freq", "100",
              "--hidden", "64", "64", "--disc-hidden", "64", "64", "--threads", "1", "--seed", "1",
              "--output-dir", str(tmp_path)]
    runs = {"sail": [], "no-adaptation": ["--no-adaptation"]}
    procs = dict(zip(runs, run_scripts(*[(*common, "--run-name", name, *flags) for name, flags in runs.items()],
                                       timeout=280)))  # both at once, one core each
    for name, proc in procs.items():
        assert proc.returncode == 0, proc.stderr[-3000:]
    final = {name: np.mean([float(r["eval_return"]) for r in read_csv(tmp_path / name)[-2:]]) for name in procs}
    assert {float(r["eval_length"]) for r in read_csv(tmp_path / "sail")} == {100.0}  # only truncated
    assert final["sail"] > 3 * teacher_return
    assert final["no-adaptation"] < 2 * teacher_return
    assert int(read_csv(tmp_path / "sail")[-1]["promotions"]) > 0


def test_ctrl_c_or_sigterm_stops_cleanly_with_a_checkpoint_that_resumes(tmp_path, poor_hopper_demos, capsys):
    """Ctrl-C, kill, timeout and job schedulers all stop a run the same way: a final checkpoint,
    the CSV intact, the shell's exit code, and --resume goes on from there."""
    import signal
    import time
    codes = {"SIGINT": 130, "SIGTERM": 143}
    procs = {signame: subprocess.Popen(  # one run per signal, side by side (a 2-core machine)
        [sys.executable, "sail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos, "--total-timesteps", "1000000",
         "--learning-starts", "400", "--eval-freq", "500", "--output-dir", str(tmp_path), "--run-name", signame, *TINY],
        cwd=HERE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for signame in codes}
    steps = {}
    for signame, proc in procs.items():
        run_dir = tmp_path / signame
        deadline = time.time() + 120
        while not (run_dir / "progress.csv").exists() and time.time() < deadline:
            time.sleep(0.2)
        time.sleep(0.3)  # some steps past the evaluation (the next is 500 steps away), whose time must be kept too
        proc.send_signal(getattr(signal, signame))
    for signame, proc in procs.items():
        run_dir = tmp_path / signame
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == codes[signame], err[-3000:]
        assert "Traceback" not in err and "--resume" in out
        rows = read_csv(run_dir)
        assert rows and list(rows[0]) == PROGRESS_COLUMNS
        loop = torch.load(run_dir / "checkpoint.pt", weights_only=True)["loop"]
        steps[signame] = loop["global_step"]
        assert steps[signame] > int(rows[-1]["global_step"])
        assert loop["train_time"] > float(rows[-1]["time"])  # the seconds after the last row are not lost
    # a flag that a resumed run cannot honour is one line, also when given with its default value
    import sail
    for flag in (["--lr", "3e-4"], ["--env", "Walker2d-v5"]):
        assert_one_line_error(main_in_process(sail.main, ["--resume", str(tmp_path / "SIGINT"), *flag], capsys))
    resumed = run_scripts(*[("sail.py", "--resume", str(tmp_path / signame), "--total-timesteps", "1000")
                            for signame in codes])  # each to its next evaluation
    for signame, proc in zip(codes, resumed):
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert int(read_csv(tmp_path / signame)[-1]["global_step"]) > steps[signame]


def test_ctrl_c_while_the_libraries_load_is_one_line_and_starts_nothing(tmp_path, poor_hopper_demos):
    import signal
    import time
    # the scripts install their quiet handler right after `import plumbing`, which must load no numpy or torch
    check = "import sys, plumbing; print(sorted({'numpy', 'torch'} & set(sys.modules)))"
    loaded = subprocess.run([sys.executable, "-c", check], cwd=HERE, capture_output=True, text=True)
    assert loaded.stdout.strip() == "[]", loaded.stdout + loaded.stderr
    proc = subprocess.Popen([sys.executable, "sail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos,
                             "--output-dir", str(tmp_path / "runs")], cwd=HERE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "sail.py: interrupted", err
    assert not (tmp_path / "runs").exists()


def flags_in_help(help_text):
    """The --flags a script's --help lists (--help aside)."""
    return set(re.findall(r"(?<![\w-])(--[a-z0-9][a-z0-9-]*[a-z0-9])", help_text)) - {"--help"}


def test_every_flag_the_readme_tables_name_exists(capsys, monkeypatch):
    """README shows the main flags and points to --help for the rest: each flag its tables name is one of
    sail.py's (or, in a row about another script, one of that script's)."""
    monkeypatch.setenv("COLUMNS", "10000")  # argparse's help on one line per flag
    sail_flags = flags_in_help(main_in_process(sail.main, ["--help"], capsys).stdout)
    assert len(sail_flags) > 40
    readme = open(os.path.join(HERE, "README.md")).read()
    rows = [line for line in readme.splitlines() if line.startswith("|")]
    named, scripts = set(), {}
    for row in rows:
        flags = {flag.rstrip("-") for flag in re.findall(r"(?<![\w-])(--[a-z0-9][a-z0-9-]*)", row)
                 if not flag.endswith("-")}  # not `--no-...`
        known = set(sail_flags)
        for script in set(re.findall(r"`(\w+\.py)`", row)) - {"sail.py", "test_sail.py"}:
            if script not in scripts:
                proc = run_script(script, "--help")
                assert proc.returncode == 0, proc.stderr[-3000:]
                scripts[script] = flags_in_help(proc.stdout)
            known |= scripts[script]
        assert flags <= known, (row, flags - known)
        named |= flags
    assert len(named) >= 10, named  # the tables do name flags


def test_sail_py_help_shows_every_flag_with_its_default(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "10000")
    help_text = main_in_process(sail.main, ["--help"], capsys).stdout
    blocks = [block for block in re.split(r"\n(?=  -)", help_text) if block.startswith("  --")]
    assert len(blocks) > 40 and all("(default: " in block for block in blocks), \
        [block for block in blocks if "(default: " not in block]
    for flag, default in (("--gamma", "0.99"), ("--total-timesteps", "1000000"), ("--hidden", "[256, 256]"),
                          ("--disc-negatives", "recent-after-promotion"), ("--action-cost", "reward-and-actor"),
                          ("--critic-layer-norm", "True")):
        block = next(block for block in blocks if block.startswith(f"  {flag} ") or block.startswith(f"  {flag},"))
        assert f"(default: {default})" in block, block


def test_method_names_the_preset_and_the_learner_flags_given_by_hand():
    """config.json's "method": the preset's name, with the learner flags written on the command line (not
    those of how the run is set up or stored); --method names it otherwise."""
    method = lambda *argv: sail.parse_args(list(argv)).method  # noqa: E731
    assert method() == "SAIL" and method("--algo", "sail-paper") == "SAIL-paper"
    assert method("--algo", "sail-paper", "--fixed-alpha") == "SAIL-paper (--fixed-alpha)"
    assert [method("--algo", algo) for algo in ("dac", "td3", "ircr", "rrd")] == ["DAC", "TD3 (sparse)", "IRCR", "RRD"]
    assert method("--algo", "dac", "--seed", "3", "--threads", "1", "--total-timesteps", "20000", "--output-dir", "x",
                  "--run-name", "y", "--kernels", "torch", "--eval-episodes", "2", "--num-demos", "4") == "DAC"
    assert method("--gamma", "0.995", "--no-critic-layer-norm") == "SAIL (--no-critic-layer-norm --gamma 0.995)"
    assert method("--algo", "sail-paper", "--disc-negatives", "recent") == "SAIL-paper (--disc-negatives recent)"
    assert method("--algo", "sail-paper", "--fixed-alpha", "--method", "mine") == "mine"


def test_no_script_imports_another():
    """Each script (a top-level file with `if __name__ == "__main__"`) imports only modules, never
    another script: what a script does stays in it, and a module's change reaches every script alike."""
    import ast
    files = [name for name in sorted(os.listdir(HERE)) if name.endswith(".py") and not name.startswith("test_")]
    scripts = {name[:-3] for name in files
               if re.search(r"""^if __name__ == ["']__main__["']:""", open(os.path.join(HERE, name)).read(), re.M)}
    assert {"sail", "evaluate", "bc", "gail", "make_demos", "bench", "plot"} <= scripts
    for name in files:
        imported = set()
        for node in ast.walk(ast.parse(open(os.path.join(HERE, name)).read())):
            if isinstance(node, ast.Import):
                imported |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                imported.add(node.module.split(".")[0])
        assert not imported & (scripts - {name[:-3]}), (name, imported & scripts)


def test_a_refused_resume_leaves_the_run_folder_as_it_was(tmp_path, straight_run, capsys):
    import shutil
    import sail
    run = tmp_path / "run"
    shutil.copytree(straight_run, run)
    config = (run / "config.json").read_text()
    # fewer steps than the run has taken (1000), then a checkpoint that cannot be read
    assert_one_line_error(main_in_process(sail.main, ["--resume", str(run), "--total-timesteps", "500"], capsys))
    (run / "checkpoint.pt").write_bytes((run / "checkpoint.pt").read_bytes()[:1000])
    assert_one_line_error(main_in_process(sail.main, ["--resume", str(run), "--total-timesteps", "5000"], capsys))
    assert (run / "config.json").read_text() == config


def test_resume_takes_flags_given_with_their_default_values(tmp_path):
    """`--resume RUN --total-timesteps 1000000` extends a 600-step run to 1M steps although
    1000000 is the parser's default: what counts is that the flag was written."""
    import plumbing
    import sail
    run = tmp_path / "run"
    run.mkdir()
    saved = vars(sail.parse_args(["--total-timesteps", "600", "--learning-starts", "100", "--eval-freq", "200",
                                  "--threads", "1"]))
    (run / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "given"}))
    (run / "checkpoint.pt").write_bytes(b"")
    args = sail.parse_args(["--resume", str(run), "--total-timesteps", "1000000", "--threads", "2"])
    assert args.given == {"resume", "total_timesteps", "threads"}
    resumed = plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py")
    assert (resumed.total_timesteps, resumed.threads, resumed.eval_freq) == (1_000_000, 2, 200)
    plumbing.record_resume(str(run), resumed, 600, sail.RESUMABLE)  # once the checkpoint has loaded
    config = json.loads((run / "config.json").read_text())  # the run folder says so
    assert (config["total_timesteps"], config["threads"], config["eval_freq"]) == (1_000_000, 2, 200)


def test_a_resumed_run_keeps_its_saved_flags_over_todays_defaults(tmp_path):
    import plumbing
    run = tmp_path / "run"
    run.mkdir()
    saved = vars(sail.parse_args(["--total-timesteps", "600", "--learning-starts", "100", "--eval-freq", "200"]))
    (run / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "given"} |
                                                {"return_bonus": 2.0, "action_cost": "reward"}))
    (run / "checkpoint.pt").write_bytes(b"")
    args = sail.parse_args(["--resume", str(run)])
    assert (args.return_bonus, args.action_cost) == (1.0, "reward-and-actor")  # today's defaults
    resumed = plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py")
    assert (resumed.return_bonus, resumed.action_cost, resumed.total_timesteps) == (2.0, "reward", 600)
    # a run of older code, whose config lacks a flag of today's, would silently take today's default
    older = {k: v for k, v in saved.items() if k not in ("given", "disc_negatives")}
    (run / "config.json").write_text(json.dumps(older))
    with pytest.raises(ConfigError, match="has no --disc-negatives"):
        plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py")
    # nor may a run made with a flag that has left the code resume without it
    (run / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "given"} | {"update_every": 1}))
    assert plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py").total_timesteps == 600
    (run / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "given"} | {"update_every": 2}))
    with pytest.raises(ConfigError, match="--update-every 2, which this code no longer has"):
        plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py")
    for actor_lr, resumes in ((None, True), (0.0001, False)):  # a run saved with --actor-lr (null: the default)
        (run / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != "given"} |
                                                    {"actor_lr": actor_lr}))
        if resumes:
            assert plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py").total_timesteps == 600
        else:
            with pytest.raises(ConfigError, match="--actor-lr 0.0001, which this code no longer has"):
                plumbing.resume_config(str(run), args, args.given, sail.RESUMABLE, "sail.py")


def test_loading_refuses_a_file_that_would_run_code(tmp_path, poor_hopper_demos, straight_run):
    """Checkpoints and model files are read with torch's weights-only unpickler: a shared file
    whose unpickling would run a command is refused with one line, and the command never runs."""
    import shutil
    marker = tmp_path / "code-ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    run = tmp_path / "run"
    shutil.copytree(straight_run, run)
    for name in ("checkpoint.pt", "model.pt"):
        torch.save({"loop": Payload(), "actor": Payload()}, run / name)
    for proc in run_scripts(("sail.py", "--resume", str(run)), ("evaluate.py", str(run))):
        assert_one_line_error(proc)
        assert "not a checkpoint this project wrote" in proc.stderr and "weights_only" not in proc.stderr
    assert not marker.exists()


def test_a_diverging_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, poor_hopper_demos):
    """--lr 1e12 makes the critic's weights explode within a few updates."""
    proc = run_script("sail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos, "--total-timesteps", "5000",
                      "--learning-starts", "300", "--eval-freq", "100", "--lr", "1e12",
                      "--output-dir", str(tmp_path), "--run-name", "run", *TINY)
    assert_one_line_error(proc)
    assert "non-finite loss" in proc.stderr
    state = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    assert all(torch.isfinite(p).all() for p in state["agent"]["critic"].values())


# ---------------------------------------------------------------------------------------------
# plot.py
# ---------------------------------------------------------------------------------------------

DEFAULT_CONFIG = {k: v for k, v in vars(sail.parse_args([])).items() if k != "given"}  # what sail.py saves


def test_sail_paper_is_the_defaults_with_each_addition_turned_off_and_the_baselines_keep_the_plain_learner():
    # (--return-decomposition 0 also turns off the learned action cost, which is part of it)
    additions_off = ["--return-bonus", "0", "--return-decomposition", "0", "--no-critic-layer-norm",
                     "--disc-negatives", "all", "--no-disc-action-norm", "--teacher-keep", "return"]
    paper, off = vars(sail.parse_args(["--algo", "sail-paper"])), vars(sail.parse_args(additions_off))
    # what still differs is the preset and its name, and flags that mean nothing with their addition off
    assert {k for k in paper if k != "given" and paper[k] != off[k]} == {"algo", "method", "decomposition_unit",
                                                                        "decomposition_subset"}
    defaults = sail.parse_args([])
    assert (defaults.return_bonus, defaults.return_decomposition) == (1.0, 1.0)
    for algo in ("dac", "td3", "ircr", "rrd"):
        args = sail.parse_args(["--algo", algo])
        assert not (args.critic_layer_norm or args.disc_action_norm) and args.disc_negatives == "all", algo
        assert args.return_decomposition == (1.0 if algo == "rrd" else 0.0) and args.decomposition_unit == "range"
        assert args.decomposition_subset == 64, algo  # RRD's own K
        assert args.action_cost == "none" and args.alpha == 0.0, algo


def test_the_learned_action_cost_is_a_default_that_turns_off_with_what_it_needs_unless_asked_for(capsys):
    """--action-cost reward-and-actor by default; with the decomposition off, a default that has nothing
    to act on turns off with it, while the same flag given by name is one error line."""
    assert sail.parse_args([]).action_cost == "reward-and-actor"
    assert sail.parse_args(["--return-decomposition", "0"]).action_cost == "none"
    assert sail.parse_args(["--algo", "sail-paper", "--return-decomposition", "1"]).action_cost == "none"  # the preset's
    assert sail.parse_args(["--action-cost", "reward"]).action_cost == "reward"
    assert sail.parse_args(["--return-decomposition", "0", "--action-cost", "none"]).action_cost == "none"
    for cost in ("reward", "reward-and-actor"):  # given by name, even with its default value
        with pytest.raises(SystemExit) as exit_info:
            sail.parse_args(["--return-decomposition", "0", "--action-cost", cost])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and "needs --return-decomposition" in err and len(err.splitlines()) == 1


def test_plot_table_reads_final_returns_teacher_crossings_and_promotions(tmp_path, capsys):
    """Two seeds of made-up CSVs: the table's numbers are computed from them as README says; runs are
    named and pooled by the method their config.json records, whatever their flags."""
    from plumbing import PROGRESS_COLUMNS
    runs = []
    for seed, returns, num_demos, method, gamma in (
            (1, [100, 900, 1400, 1500, 1600, 1700, 1800], 1, "SAIL", 0.99),
            (2, [100, 200, 300, 400, 500, 600, 700], 1, "SAIL", 0.995),  # the method, not the flags, pools it
            (1, [100, 200, 300, 400, 500, 600, 700], 4, "SAIL", 0.99),  # 4 episodes: apart
            (1, [100, 200, 300, 400, 500, 600, 800], 1, "SAIL (--gamma 0.995)", 0.995)):  # another method: apart
        run = tmp_path / f"Hopper-v5__run-{len(runs)}__{seed}"
        run.mkdir()
        config = {"env": "Hopper-v5", "algo": "sail", "method": method, "seed": seed, "num_demos": num_demos,
                  "demos": None, "gamma": gamma}
        (run / "config.json").write_text(json.dumps(config))
        rows = [{k: "nan" for k in PROGRESS_COLUMNS} | {"global_step": 10_000 * (i + 1), "eval_return": r,
                                                        "promotions": int(seed == 1 and i >= 2)}
                for i, r in enumerate(returns)]
        with open(run / "progress.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=PROGRESS_COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
        runs.append(str(run))
    committed = open(os.path.join(HERE, "results", "results.md")).read()
    # run folders given and no --output-dir: plots/ in the working directory, never results/
    proc = subprocess.run([sys.executable, os.path.join(HERE, "plot.py"), *runs, "--early-steps", "30000"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"wrote {os.path.join('plots', 'results.md')}" in proc.stderr
    assert open(os.path.join(HERE, "results", "results.md")).read() == committed
    table = (tmp_path / "plots" / "results.md").read_text()
    teacher = float(np.load(os.path.join(HERE, "demos", "Hopper-v5.npz"))["episode_returns"][0])
    assert f"(teacher {teacher:.0f})" in table
    # final = mean of the last 5 evaluations: 1600 and 500, so 1050 +- 550 over the seeds
    assert "| SAIL | 2 | 70k, 70k | 1050 +- 550 | 1600, 500 | 0.80x |" in table
    # first return >= teacher (1317); first promotion; the mean up to 30k: 800 and 200 over the seeds
    assert "| 30k, never | 30k, never | 500 |" in table
    teacher4 = float(np.mean(np.load(os.path.join(HERE, "demos", "Hopper-v5.npz"))["episode_returns"][:4]))
    assert f"### Hopper-v5, 4 teacher episodes (teacher {teacher4:.0f})" in table
    assert "| SAIL | 1 | 70k | 500 +- 0 | 500 |" in table
    assert "| SAIL (--gamma 0.995) | 1 | 70k | 520 +- 0 | 520 | 0.39x |" in table
    assert "target actor" not in table
    # above them the presets and baselines: the seeds' mean, median, range and bootstrap interval of the mean
    assert "| Hopper-v5 | SAIL | 2 | 1050 | 1050 | 500 to 1600 | 500 to 1600 | 0.80x |" in table
    assert "| Hopper-v5, 4 teacher episodes | SAIL | 1 | 500 | 500 | 500 |  | 0.38x |" in table
    assert "| Hopper-v5 | SAIL (--gamma 0.995) |" not in table
    # <env>.png: the presets and baselines; <env>-ablations.png: every other method, beside SAIL
    assert sorted(p.name for p in (tmp_path / "plots").glob("*.png")) == ["Hopper-v5-4demos.png",
                                                                         "Hopper-v5-ablations.png", "Hopper-v5.png"]
    # a damaged run, a run of older code that names no method, or a file as the output folder: one line,
    # nothing written
    import shutil

    import plot
    broken = tmp_path / "broken"
    shutil.copytree(runs[0], broken)
    (broken / "progress.csv").write_text((broken / "progress.csv").read_text().replace("100", "abc", 1))
    damaged_config = tmp_path / "damaged-config"
    shutil.copytree(runs[0], damaged_config)
    (damaged_config / "config.json").write_text("{")
    unnamed = tmp_path / "unnamed"
    shutil.copytree(runs[0], unnamed)
    (unnamed / "config.json").write_text(json.dumps({"env": "Hopper-v5", "algo": "sail", "num_demos": 1}))
    out = ["--output-dir", str(tmp_path / "out")]
    for argv in ([str(broken), *out], [str(damaged_config), *out], [str(unnamed), *out],
                 [runs[0], "--output-dir", os.path.join(HERE, "README.md")]):
        assert_one_line_error(main_in_process(plot.main, argv, capsys))
    assert not os.path.exists(tmp_path / "out")
    # the figures' rule: every name sail.py, bc.py and gail.py give a run without flags is a preset
    assert set(sail.PRESET_NAMES.values()) | {"BC", "GAIL", "POfD"} == set(plot.PRESETS)
    assert plot.method_name({"algo": "gail", "method": "POfD", "gamma": 0.995}) == "POfD"
    # a preset's runs on the seeds that no decision saw (6-8) stand apart in the first table, named by their seeds
    fresh = tmp_path / "Hopper-v5__run-fresh__6"
    shutil.copytree(runs[0], fresh)
    (fresh / "config.json").write_text(json.dumps(json.loads((fresh / "config.json").read_text()) | {"seed": 6}))
    assert main_in_process(plot.main, [*runs[:2], str(fresh), "--output-dir", str(tmp_path / "fresh")],
                           capsys).returncode == 0
    table = (tmp_path / "fresh" / "results.md").read_text()
    assert "| Hopper-v5 | SAIL, seeds 1, 2 | 2 | 1050 | 1050 | 500 to 1600 | 500 to 1600 | 0.80x |" in table
    assert f"| Hopper-v5 | SAIL, seeds 6 | 1 | 1600 | 1600 | 1600 |  | {1600 / teacher:.2f}x |" in table
    assert "| SAIL | 3 | 70k, 70k, 70k |" in table  # the method's own table pools every seed
    # a DAC run that names no commit is older code: a method of its own, out of the first table and <env>.png
    for name, commit in (("dac-old", None), ("dac-new", "0ee7e3e")):
        dac = tmp_path / f"Hopper-v5__{name}__1"
        shutil.copytree(runs[0], dac)
        config = json.loads((dac / "config.json").read_text()) | {"algo": "dac", "method": "DAC"}
        (dac / "config.json").write_text(json.dumps(config | ({"commit": commit} if commit else {})))
        assert main_in_process(plot.main, [str(dac), "--output-dir", str(tmp_path / name)], capsys).returncode == 0
        table = (tmp_path / name / "results.md").read_text()
        assert ("| Hopper-v5 | DAC | 1 |" in table) == bool(commit)
        assert ("| DAC (code not recorded) | 1 |" in table) != bool(commit)
    # the bootstrap interval of the mean: none for one seed, the range for two or three, about the mean +- 1.96
    # standard errors for many, and the same numbers every time
    assert np.isnan(plot.bootstrap_interval([5.0])).all()
    assert plot.bootstrap_interval([3.0] * 4) == (3.0, 3.0)
    assert plot.bootstrap_interval([1.0, 2.0]) == (1.0, 2.0) and plot.bootstrap_interval([3.0, 1.0, 2.0]) == (1.0, 3.0)
    values = np.arange(20.0)
    low, high = plot.bootstrap_interval(values)
    assert low < values.mean() < high and abs((high - low) / 2 - 1.96 * values.std() / np.sqrt(20)) < 0.2
    assert plot.bootstrap_interval(values) == (low, high)


# ---------------------------------------------------------------------------------------------
# gail.py: GAIL and POfD with TRPO
# ---------------------------------------------------------------------------------------------

def test_conjugate_gradient_solves_a_known_linear_system():
    from gail import conjugate_gradient
    torch.manual_seed(0)
    m = torch.randn(12, 12, dtype=torch.float64)
    a = m @ m.T + 0.5 * torch.eye(12, dtype=torch.float64)  # symmetric positive definite
    b = torch.randn(12, dtype=torch.float64)
    x = conjugate_gradient(lambda v: a @ v, b, iters=12)
    torch.testing.assert_close(x, torch.linalg.solve(a, b))


def test_trpo_step_improves_the_surrogate_within_the_kl_bound():
    from gail import GaussianPolicy, trpo_step
    torch.manual_seed(0)
    policy = GaussianPolicy(obs_dim=4, act_dim=2, hidden=[32, 32])
    obs = torch.randn(512, 4)
    with torch.no_grad():
        old = policy(obs)
        actions = old.sample()
    advantages = actions[:, 0] - actions[:, 1]  # better the larger a_0 - a_1: a clear direction to move
    advantages = (advantages - advantages.mean()) / advantages.std()
    for max_kl in (0.001, 0.01, 0.05):
        trial = copy.deepcopy(policy)
        stats = trpo_step(trial, obs, actions, advantages, max_kl=max_kl, damping=0.1, cg_iters=10, backtracks=10)
        with torch.no_grad():
            new = trial(obs)
            kl = torch.distributions.kl_divergence(old, new).sum(-1).mean().item()
            surrogate = (torch.exp(new.log_prob(actions).sum(-1) - old.log_prob(actions).sum(-1)) * advantages).mean()
        assert 0.0 < kl <= max_kl and stats["kl"] == pytest.approx(kl, rel=1e-4)
        assert surrogate > 0.0  # at the old policy the surrogate is mean(advantages) = 0
        assert kl > 0.3 * max_kl  # the step goes out to the bound, it does not stop short


def test_gae_bootstraps_through_truncation_and_not_through_termination():
    from gail import gae
    rewards, values, next_values = torch.ones(4), torch.zeros(4), torch.full((4,), 10.0)
    terminated, end = torch.tensor([0.0, 1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0, 1.0])
    adv = gae(rewards, values, next_values, terminated, end, gamma=0.5, lam=1.0)
    # TD errors: 1 + 0.5 * 10 = 6 where s' bootstraps, 1 at the terminal step 1; step 3 is truncated (or the
    # batch's end) and still bootstraps from V(s'). Sums: A3 = 6, A2 = 6 + 0.5 A3, A1 = 1, A0 = 6 + 0.5 A1
    torch.testing.assert_close(adv, torch.tensor([6.5, 1.0, 9.0, 6.0]))


def test_gail_and_pofd_smoke_runs_write_the_csv_and_resume_exactly(tmp_path, poor_hopper_demos, capsys):
    flags = {"gail": [], "pofd": ["--pofd"]}
    common = {algo: ["gail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos, "--steps-per-batch", "500",
                     "--eval-freq", "1000", "--eval-episodes", "1", "--hidden", "16", "16", "--disc-hidden", "16", "16",
                     "--checkpoint-freq", "1000", "--output-dir", str(tmp_path / algo), *flags[algo]] for algo in flags}
    procs = run_scripts(*[(*common[algo], "--total-timesteps", total, "--run-name", name)
                          for algo in flags for total, name in (("3000", "a"), ("1000", "b"))], at_once=2)
    assert all(proc.returncode == 0 for proc in procs), "".join(proc.stderr for proc in procs)[-3000:]
    resumed = run_scripts(*[("gail.py", "--resume", str(tmp_path / algo / "b"), "--total-timesteps", "3000")
                            for algo in flags])
    assert all(proc.returncode == 0 for proc in resumed), "".join(proc.stderr for proc in resumed)[-3000:]
    import gail
    for algo in flags:
        rows = read_csv(tmp_path / algo / "a")
        assert list(rows[0]) == PROGRESS_COLUMNS and [int(r["global_step"]) for r in rows] == [1000, 2000, 3000]
        assert all(np.isfinite(float(r["eval_return"])) and 0 < float(r["disc_teacher"]) < 1 for r in rows)
        config = json.load(open(tmp_path / algo / "a" / "config.json"))
        assert config["algo"] == algo and config["method"] == {"gail": "GAIL", "pofd": "POfD"}[algo]
        assert learning_rows(tmp_path / algo / "a") == learning_rows(tmp_path / algo / "b")
        assert_one_line_error(main_in_process(gail.main, ["--resume", str(tmp_path / algo / "b"), "--max-kl", "0.05"],
                                              capsys))
    for bad in (["--steps-per-batch", "1"], ["--max-kl", "inf"], ["--eval-freq", "5000", "--total-timesteps", "1000"]):
        assert_one_line_error(main_in_process(gail.main, [*common["gail"][1:], "--run-name", "c", *bad], capsys))
    assert not os.path.exists(tmp_path / "gail" / "c")


def test_gail_imitates_a_good_teacher_on_a_small_task(tmp_path):
    """PointMass: the teacher pushes with +1 (return ~96); a random policy scores about 0. GAIL
    sees only the teacher's (s, a) and the sparse episodic return, which it ignores: it must
    come close to the teacher within 15k env steps (seed 1: 41, 61, 84, 93, 96 at 3k-15k steps, 2026-11-23)."""
    env_id = "test_sail:PointMass-v0"
    env = make_env(env_id, seed=0, sparse=False, time_feature=False)
    episodes = [rollout(env, lambda obs: np.array([1.0], np.float32)) for _ in range(4)]
    demos = str(tmp_path / "PointMass.npz")
    save_demos(demos, episodes, env_id)
    teacher_return = episodes[0]["episodic_return"]
    proc = run_script("gail.py", "--env", env_id, "--demos", demos, "--total-timesteps", "15000",
                      "--steps-per-batch", "1000", "--eval-freq", "3000", "--eval-episodes", "2",
                      "--hidden", "32", "32", "--disc-hidden", "32", "32", "--output-dir", str(tmp_path),
                      # 15 batches: D needs more than the default one step per batch of a 1M-step run
                      "--disc-lr", "1e-3", "--disc-batch-size", "250", "--run-name", "gail", timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    returns = [float(r["eval_return"]) for r in read_csv(tmp_path / "gail")]
    assert returns[0] < 0.6 * teacher_return  # it starts far from the teacher
    assert np.mean(returns[-2:]) > 0.9 * teacher_return


def test_tensorboard_logs_the_csv_numbers(tmp_path, poor_hopper_demos):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    proc = run_script("sail.py", "--env", "Hopper-v5", "--demos", poor_hopper_demos, "--total-timesteps", "800",
                      "--learning-starts", "700", "--eval-freq", "400", "--disc-freq", "100", "--tensorboard",
                      "--output-dir", str(tmp_path), "--run-name", "run", *TINY)
    assert proc.returncode == 0, proc.stderr[-3000:]
    events = EventAccumulator(str(tmp_path / "run"))
    events.Reload()
    logged = [(e.step, e.value) for e in events.Scalars("progress/eval_return")]
    rows = read_csv(tmp_path / "run")
    assert [step for step, _ in logged] == [400, 800]
    assert [v for _, v in logged] == pytest.approx([float(r["eval_return"]) for r in rows], rel=1e-6)  # float32


# ---------------------------------------------------------------------------------------------
# results/grid.py: grids through GNU parallel and SLURM job arrays
# ---------------------------------------------------------------------------------------------

def load_grid_module():
    """results/grid.py, a script in a folder that is not a package, as a module."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("grid", os.path.join(HERE, "results", "grid.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_grid_runs_through_gnu_parallel_resumes_and_maps_slurm_tasks(tmp_path, capsys):
    grid = os.path.join(HERE, "results", "grid.py")
    grid_module = load_grid_module()
    runs = str(tmp_path / "runs")
    lines = main_in_process(grid_module.main, ["list", "smoke", runs], capsys).stdout.splitlines()
    assert len(lines) == 2 and all(" run " + runs + " Pendulum-v1__td3__" in line for line in lines)
    # the SLURM array: task i runs line i
    script = main_in_process(grid_module.main, ["slurm", "smoke", runs], capsys).stdout
    assert "#SBATCH --array=1-2" in script and f'results/grid.py task smoke {runs} "$SLURM_ARRAY_TASK_ID"' in script
    for i, line in enumerate(lines, start=1):
        assert main_in_process(grid_module.main, ["task", "smoke", runs, str(i), "--dry-run"],
                               capsys).stdout.strip() == line
    assert_one_line_error(main_in_process(grid_module.main, ["task", "smoke", runs, "3", "--dry-run"], capsys))
    assert_one_line_error(main_in_process(grid_module.main, ["run", runs], capsys))  # no NAME and SCRIPT
    assert_one_line_error(main_in_process(grid_module.main, ["local", "smoke", grid], capsys))  # a file
    # locally through GNU parallel (a second call starts nothing: its job log); beside it, a run stopped
    # half-way, which continues from its checkpoint when its line runs again
    import shlex
    flags = shlex.split(lines[0].split(" sail.py ")[1])  # --method NAME is quoted: its name has spaces
    half = [*flags[:flags.index("--total-timesteps") + 1], "200", *flags[flags.index("--total-timesteps") + 2:]]
    local, stopped = run_scripts((grid, "local", "smoke", runs, "--jobs", "2"),
                                 (grid, "run", str(tmp_path / "other"), "r", "sail.py", *half))
    assert local.returncode == 0 and stopped.returncode == 0
    for seed in (1, 2):
        assert int(read_csv(tmp_path / "runs" / f"Pendulum-v1__td3__{seed}")[-1]["global_step"]) == 400
        # the line's --method names the run; the run folder is given as a path from the repository
        with open(tmp_path / "runs" / f"Pendulum-v1__td3__{seed}" / "config.json") as f:
            config = json.load(f)
        assert config["method"] == flags[flags.index("--method") + 1]
        assert not any(os.path.isabs(word) for word in shlex.split(config["command"])[1:]), config["command"]
    before = (tmp_path / "runs" / "joblog").read_text()
    assert run_script(grid, "local", "smoke", runs, "--jobs", "2").returncode == 0
    assert (tmp_path / "runs" / "joblog").read_text() == before
    assert int(read_csv(tmp_path / "other" / "r")[-1]["global_step"]) == 200
    proc = run_script(grid, "run", str(tmp_path / "other"), "r", "sail.py", *flags)
    assert proc.returncode == 0 and "--resume" in proc.stdout
    assert [int(r["global_step"]) for r in read_csv(tmp_path / "other" / "r")] == [200, 400]
    # BC has no env steps and no checkpoint: stopped after its halfway row it is not finished, but begun again
    bc = tmp_path / "bc"
    bc.mkdir()
    (bc / "progress.csv").write_text("global_step,eval_return\n0,10.0\n")
    assert not grid_module.finished(str(bc), None)
    (bc / "model.pt").write_bytes(b"")
    assert grid_module.finished(str(bc), None)


def test_every_committed_run_is_what_its_grid_line_runs_with_sail_py_today():
    """A committed run's config (its method, env, seed, teacher episodes and every learner flag) is what its
    grid line gives sail.py as it is now: a default that changes must leave the grids of the older runs
    writing the old value out. Every committed run outside results/archive/ is some grid line's, named as a new run
    of that line is."""
    results = os.path.join(HERE, "results")
    folders = {os.path.relpath(os.path.dirname(os.path.dirname(path)), results)
               for path in glob.glob(os.path.join(results, "**", "config.json"), recursive=True)}
    folders = sorted(folder for folder in folders if folder.split(os.sep)[0] != "archive")  # their code left
    assert {"runs", os.path.join("long", "runs"), "weak-k256"} <= set(folders), folders
    committed = {os.path.join(folder, name) for folder in folders for name in os.listdir(os.path.join(results, folder))
                 if os.path.isdir(os.path.join(results, folder, name))}
    found, checked = set(), 0
    for entries in load_grid_module().GRIDS.values():
        for name, script, flags in entries:
            for folder in folders:
                path = os.path.join(results, folder, name, "config.json")
                if not os.path.isfile(path):
                    continue
                found.add(os.path.join(folder, name))
                with open(path) as f:
                    config = json.load(f)
                if script != "sail.py":  # bc.py and gail.py name their runs themselves
                    assert config["method"] == {"bc.py": "BC", "gail.py": "POfD" if "--pofd" in flags else "GAIL"}[
                        script], path
                    continue
                args = vars(sail.parse_args(flags))
                keys = [key for key in args if key not in sail.SETUP and key != "given"] + [
                    "method", "env", "seed", "num_demos"]
                saved = {key: config.get(key, "(missing)") for key in keys}
                wanted = {key: args[key] for key in keys}
                assert saved == wanted, (path, {key: (saved[key], wanted[key]) for key in keys
                                                if saved[key] != wanted[key]})
                checked += 1
    assert found == committed, sorted(committed - found)
    assert checked > 150


def test_grid_defaults_are_sail_py_defaults():
    """grid.py's DEFAULTS, which new grids build on, is what sail.py runs with no learner flag given."""
    defaults = vars(sail.parse_args(load_grid_module().DEFAULTS))
    plain = vars(sail.parse_args([]))
    keys = [key for key in plain if key not in sail.SETUP and key != "given"]
    assert {key: defaults[key] for key in keys} == {key: plain[key] for key in keys}


def test_the_cpu_a_results_paragraph_names_is_the_one_its_runs_recorded():
    """Where a paragraph of a results write-up names a CPU ("family F model M") and the runs it is about,
    each of those runs' config.json recorded that CPU: a speed or a date is only as good as its machine."""
    recorded = {}
    for path in glob.glob(os.path.join(HERE, "results", "**", "config.json"), recursive=True):
        with open(path) as f:
            recorded.setdefault(os.path.basename(os.path.dirname(path)), set()).add(json.load(f).get("cpu", ""))
    checked = 0
    for doc in glob.glob(os.path.join(HERE, "results", "**", "README.md"), recursive=True):
        for paragraph in re.split(r"\n\s*\n|\n- ", open(doc).read()):
            named = {(int(f), int(m)) for f, m in re.findall(r"family (\d+),? model (\d+)", paragraph)}
            runs = set(re.findall(r"`(\w+-v5__[\w-]+__\d+)`", paragraph)) & recorded.keys()
            if len(named) != 1 or not runs:
                continue
            for run in runs:  # a name can be in two folders (runs/ and archive/): one of them on that CPU
                cpus = {tuple(map(int, cpu))
                        for cpu in re.findall(r"family (\d+), model (\d+)", " ".join(recorded[run]))}
                assert cpus & named, (doc, run, recorded[run], named)
                checked += 1
    assert checked >= 8


def test_grid_list_into_a_closed_pipe_is_quiet():
    """`grid.py list GRID | head -1`: the reader closes the pipe early; no traceback."""
    proc = subprocess.Popen([sys.executable, os.path.join(HERE, "results", "grid.py"), "list", "learning"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # before the script writes a line: its first write meets a closed pipe
    stderr = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 1 and stderr == "", stderr


def test_bench_times_every_part_with_sail_defaults():
    """bench.py drives sail.py's update and loop directly, so a change of sail.py's defaults (the
    return bonus needs episode returns in the buffers) must keep it running end to end."""
    proc = run_script("bench.py", "--threads", "1", "--hidden", "16", "--updates", "30", "--env-steps", "100",
                      "--warmup", "200", "--skip-memory")
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[1].startswith("CPU: ")
    for part in ("1. ", "2. updates/s", "3. env steps/s"):
        assert any(line.startswith(part) for line in lines), proc.stdout
    # the defaults are timed beside the paper's SAIL and the plain loop, and two runs side by side
    end_to_end = [line for line in lines if line.startswith("3. env steps/s")]
    assert "SAIL's defaults" in end_to_end[0] and "the paper's SAIL" in end_to_end[0], proc.stdout
    assert "side by side" in end_to_end[-1], proc.stdout


def test_a_run_folder_in_use_refuses_a_second_process_and_a_resume_says_where_it_goes_on(tmp_path, straight_run):
    """A run folder is locked by the process that runs it (an OS lock, gone with the process): a second
    --resume of it is one line and writes nothing; once the lock is gone the same --resume goes on."""
    import fcntl
    import shutil
    run = tmp_path / "run"
    shutil.copytree(straight_run, run)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with open(run / ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        proc = run_script("sail.py", "--resume", str(run), "--total-timesteps", "1250")
    assert_one_line_error(proc)
    assert "in use" in proc.stderr
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    proc = run_script("sail.py", "--resume", str(run), "--total-timesteps", "1250")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"resumed {run} at step 1000 of 1250" in proc.stdout
    assert json.loads((run / "config.json").read_text())["total_timesteps"] == 1250


def test_resuming_a_finished_run_or_another_scripts_run_is_one_line(tmp_path, straight_run):
    import shutil
    finished, other = tmp_path / "finished", tmp_path / "other"
    shutil.copytree(straight_run, finished)
    shutil.copytree(straight_run, other)
    config = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps(config | {"script": "gail.py"}))
    done, wrong_script, gail_on_sail, evaluate_gail = run_scripts(
        ("sail.py", "--resume", str(finished)), ("sail.py", "--resume", str(other)),
        ("gail.py", "--resume", str(finished)), ("evaluate.py", str(other)))
    for proc in (done, wrong_script, gail_on_sail, evaluate_gail):
        assert_one_line_error(proc)
    assert "a run of gail.py; evaluate.py plays" in evaluate_gail.stderr
    assert "finished its 1000 steps" in done.stderr
    assert "a run of gail.py, not of sail.py" in wrong_script.stderr
    assert "a run of sail.py, not of gail.py" in gail_on_sail.stderr


def test_flag_values_that_would_train_nothing_or_escape_the_output_folder_are_one_line(tmp_path):
    out = tmp_path / "runs"
    procs = run_scripts(*(("sail.py", *flags, "--output-dir", str(out)) for flags in (
        ["--tau", "5"], ["--tau", "0"], ["--gamma", "1.5"], ["--lr", "0"], ["--disc-lr", "0"],
        ["--total-timesteps", "5000", "--eval-freq", "1000"],  # ends inside the 10k random steps
        ["--env", "Hopper-v5", "--run-name", "../escaped", "--total-timesteps", "20000"])))
    for proc in procs:
        assert_one_line_error(proc)
    assert "a folder name, not a path" in procs[-1].stderr
    assert not (tmp_path / "escaped").exists()


def test_a_full_disk_keeps_the_previous_file_and_says_so_in_one_line(tmp_path):
    import plumbing
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"the previous checkpoint")

    def full_disk(f):
        f.write(b"half of it")
        raise OSError(28, "No space left on device")
    with pytest.raises(ConfigError, match="No space left on device; the previous checkpoint.pt is kept"):
        plumbing.atomic_write(str(path), full_disk)
    assert path.read_bytes() == b"the previous checkpoint"
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no temp file left


def test_a_non_finite_loss_says_whether_a_checkpoint_is_kept(tmp_path):
    import plumbing
    plumbing.check_finite({"critic_loss": torch.tensor(1.0)}, "at step 5", str(tmp_path))
    with pytest.raises(ConfigError, match="had written no checkpoint yet"):
        plumbing.check_finite({"critic_loss": torch.tensor(float("inf"))}, "at step 5", str(tmp_path))
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match="last good checkpoint in .* is kept"):
        plumbing.check_finite({"critic_loss": torch.tensor(float("nan"))}, "at step 5", str(tmp_path))


def test_the_bar_shows_no_time_left_during_the_warm_up(capsys):
    import plumbing
    bar = plumbing.progress_bar(1000, 0, "sail Hopper-v5", warm_up=500)
    bar.update(100)
    during = str(bar)
    bar.update(500)
    after = str(bar)
    bar.close()
    assert "warm-up" in during and "<" not in during  # tqdm writes the time left as "<" + time
    assert "warm-up" not in after and "<" in after


def test_a_resumed_bar_shows_the_last_evaluation_and_one_teacher_episode_is_singular(straight_run):
    import plumbing
    row = read_csv(straight_run)[-1]
    bar = plumbing.progress_bar(2000, int(row["global_step"]), "sail", 500,
                                {k: float(v) for k, v in row.items()})
    text = str(bar)
    bar.close()
    assert f"eval={float(row['eval_return']):.0f}" in text and "1000/2000" in text
    assert plumbing.count(1, "episode") == "1 episode" and plumbing.count(4, "episode") == "4 episodes"
