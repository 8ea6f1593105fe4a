"""The sparse episodic MuJoCo setting of SAIL (paper, section "Problem Setting").

The learner never sees a per-step reward: every step returns 0.0 except the one on which the
episode ends, which returns the episodic return r_e, the sum of the dense rewards of the whole
episode. Two optional observation features follow the authors' code and DAC:

- a time feature 1 - t/T, so that a policy can tell how much of the horizon is left;
- an absorbing-state indicator: an episode that terminates before the time limit moves to an
  absorbing state that loops to itself (DAC, Kostrikov et al. 2019).

Demonstrations are stored without features; `add_features` turns a recorded episode into the
transitions the wrappers below would have produced online, with the same helper functions.
"""

import copy

import gymnasium as gym
import numpy as np

try:  # loaded with the scripts' imports, where Ctrl-C exits at once: an import of MuJoCo that Ctrl-C
    # cuts short reads as ImportError, which gym.make would report as "MuJoCo is not installed"
    import mujoco  # noqa: F401
except ImportError:
    pass  # make_env says so for the env that needs it

from plumbing import ConfigError, first_line


def time_left(t, max_steps):
    """The time feature 1 - t/T: 1.0 at reset, 0.0 at the time limit (t may be an array)."""
    return np.float32(1.0 - np.asarray(t) / max_steps)


def absorbing_state(obs_dim):
    """The absorbing state: all zeros but the indicator (the last dimension)."""
    state = np.zeros(obs_dim + 1, dtype=np.float32)
    state[-1] = 1.0
    return state


class SparseEpisodicReward(gym.Wrapper):
    """Reward 0 on every step but the last, which carries the episodic return r_e.

    It wraps gymnasium's RecordEpisodeStatistics, whose info["episode"]["r"] is the sum of the
    dense rewards. The info dict is replaced: MuJoCo envs put the reward terms in it
    (reward_forward, x_velocity, ...), and none of that may reach the learner. At the end of an
    episode info holds only `episode` (return "r", length "l"), for logging and promotion.
    """

    def reset(self, **kwargs):
        obs, _ = self.env.reset(**kwargs)
        return obs, {}

    def step(self, action):
        obs, _, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            return obs, float(info["episode"]["r"]), terminated, truncated, {"episode": info["episode"]}
        return obs, 0.0, terminated, truncated, {}


class TimeFeature(gym.ObservationWrapper):
    """Appends 1 - t/T to the observation (the authors' code; T is the env's time limit)."""

    def __init__(self, env, max_steps):
        super().__init__(env)
        self.max_steps, self.t = max_steps, 0
        low = np.append(env.observation_space.low, 0.0).astype(np.float32)
        high = np.append(env.observation_space.high, 1.0).astype(np.float32)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)

    def reset(self, **kwargs):
        self.t = 0
        return super().reset(**kwargs)

    def step(self, action):
        self.t += 1
        return super().step(action)

    def observation(self, obs):
        return np.append(obs, time_left(self.t, self.max_steps)).astype(np.float32)


class AbsorbingState(gym.Wrapper):
    """Absorbing states of DAC: one indicator dimension, 0 for real states.

    When the wrapped env terminates (not on truncation by the time limit), this wrapper does not
    end the episode: it returns the absorbing state with terminated=False, and the next step,
    whatever the action, loops from the absorbing state to itself and ends the episode as
    truncated. The learner therefore bootstraps through both transitions (the absorbing state is
    not terminal for the critic; its value is learned like any other), at the cost of one extra
    env step per terminated episode. The episode's reward (the episodic return in the sparse
    setting) is given on that final step, so "reward only when the episode ends" still holds.
    """

    def __init__(self, env):
        super().__init__(env)
        obs_dim = env.observation_space.shape[0]
        low = np.append(env.observation_space.low, 0.0).astype(np.float32)
        high = np.append(env.observation_space.high, 1.0).astype(np.float32)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self.absorbing = absorbing_state(obs_dim)
        self.in_absorbing, self.pending = False, None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self.in_absorbing, self.pending = False, None
        return np.append(obs, 0.0).astype(np.float32), info

    def step(self, action):
        if self.in_absorbing:  # the absorbing state's self-loop; then the episode is over
            reward, info = self.pending
            self.in_absorbing, self.pending = False, None
            return self.absorbing.copy(), reward, False, True, info
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated:
            self.in_absorbing, self.pending = True, (reward, info)
            return self.absorbing.copy(), 0.0, False, False, {}
        return np.append(obs, 0.0).astype(np.float32), reward, False, truncated, info


def make_env(env_id, seed, sparse=True, time_feature=True, absorbing=False, render_mode=None):
    """Builds `env_id` seeded with `seed` (env, action space, observation space).

    sparse:         reward 0 except the episodic return on the last step (False: dense reward,
                    used to train the teacher only).
    time_feature:   append 1 - t/T to the observation.
    absorbing:      DAC's absorbing-state indicator and self-loop.
    render_mode:    gymnasium's, e.g. "rgb_array" for videos.
    Raises ConfigError for an unknown id, a non-Box action space or a non-flat observation space.
    """
    # render_mode only when asked: an env of the user's own need not accept the keyword
    options = {"render_mode": render_mode} if render_mode else {}
    try:
        env = gym.make(env_id, **options)
    except (gym.error.Error, ImportError, AttributeError, ValueError) as e:  # also "nosuchmodule:Foo-v0"
        raise ConfigError(f"unknown environment {env_id!r}: {first_line(e)}") from None
    if not isinstance(env.action_space, gym.spaces.Box):
        raise ConfigError(f"{env_id} has a {type(env.action_space).__name__} action space; "
                          "these learners need a continuous Box action space")
    if not isinstance(env.observation_space, gym.spaces.Box) or len(env.observation_space.shape) != 1:
        raise ConfigError(f"{env_id} needs a flat Box observation space")
    max_steps = env.spec.max_episode_steps or 1000
    env = gym.wrappers.RecordEpisodeStatistics(env)  # info["episode"]["r"]: the dense episodic return
    if sparse:
        env = SparseEpisodicReward(env)
    if time_feature:
        env = TimeFeature(env, max_steps)
    if absorbing:
        env = AbsorbingState(env)
    env.max_episode_steps = max_steps
    env.reset(seed=seed)
    env.action_space.seed(seed)
    env.observation_space.seed(seed)
    return env


def add_features(episode, max_steps, time_feature=True, absorbing=False):
    """The transitions that the wrappers above produce online, for one recorded episode.

    `episode` holds raw arrays observations, actions, next_observations (T rows each) and the
    bool `terminated` (the episode ended in a terminal state, not by the time limit).
    Returns (obs, actions, next_obs, terminated) float32 arrays as the learner stores them.
    """
    obs = np.asarray(episode["observations"], dtype=np.float32)
    actions = np.asarray(episode["actions"], dtype=np.float32)
    next_obs = np.asarray(episode["next_observations"], dtype=np.float32)
    T = len(obs)
    terminated = np.zeros(T, dtype=np.float32)
    if episode["terminated"]:
        terminated[-1] = 1.0
    if time_feature:
        t = np.arange(T + 1)
        obs = np.column_stack([obs, time_left(t[:-1], max_steps)])
        next_obs = np.column_stack([next_obs, time_left(t[1:], max_steps)])
    if absorbing:
        obs = np.column_stack([obs, np.zeros(T, np.float32)])
        next_obs = np.column_stack([next_obs, np.zeros(T, np.float32)])
        if episode["terminated"]:  # s_T becomes the absorbing state, which then loops once
            absorbing_obs = absorbing_state(obs.shape[1] - 1)
            next_obs[-1] = absorbing_obs
            terminated[-1] = 0.0
            obs = np.vstack([obs, absorbing_obs])
            next_obs = np.vstack([next_obs, absorbing_obs])
            actions = np.vstack([actions, np.zeros_like(actions[:1])])
            terminated = np.append(terminated, np.float32(0.0))
    return obs.astype(np.float32), actions, next_obs.astype(np.float32), terminated



def rollout(env, policy, frames=None):
    """Runs one episode of `policy` (obs -> action) and returns its transitions; with a list
    `frames`, appends env.render() after the reset and after every step.

    The dict holds observations, actions, rewards, next_observations (as the env gave them),
    terminated / truncated for the episode, and episodic_return and length, the dense return and the
    env's own step count (RecordEpisodeStatistics' info["episode"]; DAC's absorbing self-loop not counted).
    """
    obs, _ = env.reset()
    if frames is not None:
        frames.append(env.render())
    steps = []
    while True:
        action = policy(obs)
        next_obs, reward, terminated, truncated, info = env.step(action)
        if frames is not None:
            frames.append(env.render())
        steps.append((obs, action, reward, next_obs))
        obs = next_obs
        if terminated or truncated:
            break
    observations, actions, rewards, next_observations = (np.array(x) for x in zip(*steps))
    return {"observations": observations, "actions": actions, "rewards": rewards,
            "next_observations": next_observations, "terminated": bool(terminated),
            "truncated": bool(truncated), "episodic_return": float(info["episode"]["r"]),
            "length": int(info["episode"]["l"])}


# ---------------------------------------------------------------------------------------------
# Exact mid-episode checkpoints: the env's full state (simulator, wrappers' counters, RNGs)
# ---------------------------------------------------------------------------------------------

_PLAIN = (bool, int, float, str, type(None), np.number, np.ndarray, tuple, dict)
# The frames and centres of mass that MuJoCo's last substep computed before it moved the bodies, which an
# env may read before its next step (Ant-v5's xy position of the torso, Humanoid-v5's centre of mass, for
# the velocity in the reward): mj_forward would recompute them at the current state, a substep later
_KINEMATICS = ("xpos", "xquat", "xmat", "xipos", "ximat", "xanchor", "xaxis", "geom_xpos", "geom_xmat",
               "site_xpos", "site_xmat", "subtree_com")


def get_env_state(env):
    """Everything needed to continue `env` exactly where it is, also in mid-episode."""
    layers, layer = [], env
    while isinstance(layer, gym.Wrapper):
        layers.append({k: copy.deepcopy(v) for k, v in vars(layer).items() if k != "env" and isinstance(v, _PLAIN)})
        layer = layer.env
    base = layer
    state = {"wrappers": layers, "np_random": copy.deepcopy(base.np_random.bit_generator.state),
             "action_space": copy.deepcopy(env.action_space.np_random.bit_generator.state)}
    if hasattr(base, "model") and hasattr(base, "data"):  # MuJoCo: the full integration state
        import mujoco
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        sim = np.empty(mujoco.mj_stateSize(base.model, spec))
        mujoco.mj_getState(base.model, base.data, sim, spec)
        state["mujoco"] = sim
        state["mujoco_kinematics"] = {name: getattr(base.data, name).copy() for name in _KINEMATICS}
    elif hasattr(base, "state"):  # classic-control style envs
        state["base_state"] = copy.deepcopy(base.state)
    return state


class EnvState:
    """An env as a checkpoint part (plumbing.save_checkpoint): its exact state, mid-episode too."""

    def __init__(self, env):
        self.env = env

    def state_dict(self):
        return get_env_state(self.env)

    def load_state_dict(self, state):
        set_env_state(self.env, state)


def set_env_state(env, state):
    layer = env
    for saved in state["wrappers"]:
        for k, v in saved.items():
            setattr(layer, k, copy.deepcopy(v))
        layer = layer.env
    layer.np_random.bit_generator.state = state["np_random"]
    env.action_space.np_random.bit_generator.state = state["action_space"]
    if "mujoco" in state:
        import mujoco
        mujoco.mj_setState(layer.model, layer.data, state["mujoco"], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(layer.model, layer.data)
        for name, value in state.get("mujoco_kinematics", {}).items():  # absent in checkpoints made before
            getattr(layer.data, name)[...] = value
    elif "base_state" in state:
        layer.state = copy.deepcopy(state["base_state"])


def evaluate_policy(env, policy, episodes):
    """The evaluation of a deterministic policy: mean and std of the dense episodic return over
    `episodes` episodes, and their mean length (on Hopper or Walker2d a short one is a fall)."""
    runs = [rollout(env, policy) for _ in range(episodes)]
    returns = [run["episodic_return"] for run in runs]
    return {"eval_return": float(np.mean(returns)), "eval_return_std": float(np.std(returns)),
            "eval_length": float(np.mean([run["length"] for run in runs]))}
