"""The two buffers of SAIL: the self replay buffer R_B and the adaptive teacher buffer R_E.

Both hold float32 torch tensors (a 1e6-transition Walker2d buffer with the time feature is
about 0.15 GB) and sample with torch's global RNG, so a fixed torch seed fixes the batches.
The demo file format is documented in README.md; `load_demos` checks it.
"""

import os
import warnings

import numpy as np
import torch

from envs import add_features
from plumbing import ConfigError, atomic_write, first_line

DEMO_KEYS = ("observations", "actions", "next_observations", "rewards", "terminations",
             "truncations", "episode_lengths", "episode_returns", "env_id")


class ReplayBuffer:
    """R_B: every transition the agent generated, a ring of `capacity` transitions.

    Storage is preallocated; `add` writes one row through numpy views of the tensors, so a step
    costs no allocation. `rewards` is the env's reward (dense for the teacher, sparse episodic
    for SAIL, where only the TD3-sparse baseline reads it).
    """

    def __init__(self, obs_dim, act_dim, capacity):
        self.capacity, self.size, self.ptr = int(capacity), 0, 0
        self.obs = torch.zeros(self.capacity, obs_dim)
        self.actions = torch.zeros(self.capacity, act_dim)
        self.rewards = torch.zeros(self.capacity)
        self.next_obs = torch.zeros(self.capacity, obs_dim)
        self.terminated = torch.zeros(self.capacity)
        self._views = [t.numpy() for t in self.tensors()]
        # the episodic return of each transition's episode, NaN while that episode is running
        self.episode_returns = torch.full((self.capacity,), float("nan"))
        self._returns_view = self.episode_returns.numpy()
        # where each finished transition's episode starts in the ring, and its length (for
        # --return-decomposition, which samples steps of one episode together)
        self.episode_starts = torch.zeros(self.capacity, dtype=torch.long)
        self.episode_lengths = torch.zeros(self.capacity, dtype=torch.long)

    def tensors(self):
        return self.obs, self.actions, self.rewards, self.next_obs, self.terminated

    def add(self, obs, action, reward, next_obs, terminated):
        for view, value in zip(self._views, (obs, action, reward, next_obs, terminated)):
            view[self.ptr] = value
        self._returns_view[self.ptr] = np.nan
        self.ptr = (self.ptr + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size):
        """Uniform batch (obs, actions, rewards, next_obs, terminated) from the whole buffer."""
        return self.gather(torch.randint(0, self.size, (batch_size,)))

    def sample_steps(self, batch_size, n_step, with_returns=False):
        """A batch of runs of up to `n_step` consecutive transitions of one episode, each from a
        uniformly drawn first one (with `with_returns`, drawn from the finished episodes only):
        (obs, actions, rewards, next_obs, terminated) of shape (batch_size, n_step, ...), a mask
        that is 1 for the steps inside the first one's episode (R_B's newest step ends a running
        one), and with `with_returns` the episodic returns (else None)."""
        idx = self.finished_indices(batch_size) if with_returns else torch.randint(0, self.size, (batch_size,))
        window, mask = step_window(idx, self.steps_left(idx) if n_step > 1 else None, n_step, self.capacity)
        return self.gather(window), mask, (self.episode_returns[idx] if with_returns else None)

    def steps_left(self, idx):
        """How many transitions follow each of `idx` in its episode, as far as R_B holds them: to
        the episode's last step if it has ended, else to the newest transition."""
        finished = ~self.episode_returns[idx].isnan()
        last = torch.where(finished, self.episode_starts[idx] + self.episode_lengths[idx] - 1,
                           torch.tensor(self.ptr - 1))
        return (last - idx) % self.capacity

    def finished_indices(self, n):
        """n uniform indices of transitions whose episode has ended."""
        idx = torch.randint(0, self.size, (n,))
        running = self.episode_returns[idx].isnan()
        for _ in range(1000):  # resample what fell in the running episode (usually a few of 256)
            if not running.any():
                return idx
            idx[running] = torch.randint(0, self.size, (int(running.sum()),))
            running = self.episode_returns[idx].isnan()
        raise ConfigError("no finished episode in the self buffer to sample from: raise --learning-starts above "
                          "the length of an episode")

    def end_episode(self, start, episodic_return):
        """Marks the transitions from index `start` up to the newest with their episode's return."""
        length = (self.ptr - start) % self.capacity
        idx = torch.arange(start, start + length) % self.capacity
        self.episode_returns[idx] = float(episodic_return)
        self.episode_starts[idx], self.episode_lengths[idx] = start, length

    def sample_episode_subsets(self, num_episodes, subset_size):
        """For randomized return decomposition: `num_episodes` finished episodes (drawn in
        proportion to their length) and `subset_size` distinct steps of each one, uniformly (all
        of an episode's steps if it has fewer). Returns obs, actions, next_obs of shape
        (num_episodes, subset_size, dim), a mask that is 0 where a column is padding or its step
        was since overwritten by a newer episode, and each episode's return and length."""
        anchors = self.finished_indices(num_episodes)
        starts, lengths = self.episode_starts[anchors], self.episode_lengths[anchors]
        # random keys sorted: the first subset_size positions are a uniform subset without replacement
        positions = torch.arange(max(int(lengths.max()), subset_size))
        keys = torch.rand(num_episodes, len(positions)).masked_fill(positions >= lengths[:, None], 2.0)
        offsets = keys.argsort(dim=1)[:, :subset_size]
        idx = (starts[:, None] + offsets) % self.capacity
        mask = ((offsets < lengths[:, None]) & (self.episode_starts[idx] == starts[:, None])
                & (self.episode_lengths[idx] == lengths[:, None]) & ~self.episode_returns[idx].isnan()).float()
        return self.obs[idx], self.actions[idx], self.next_obs[idx], mask, self.episode_returns[anchors], lengths

    def sorted_episode_returns(self):
        """The episodic returns of the finished transitions, one per transition, sorted ascending."""
        returns = self.episode_returns[:self.size]
        return returns[~returns.isnan()].sort().values

    def sample_recent(self, batch_size, window):
        """Uniform batch from the `window` most recent transitions (on-policy ablation)."""
        window = min(window, self.size)
        back = torch.randint(1, window + 1, (batch_size,))
        return self.gather((self.ptr - back) % self.capacity)

    def latest(self, n):
        """The n most recent transitions (obs, actions, next_obs, terminated): the episode that
        just ended, for the teacher buffer."""
        obs, actions, _, next_obs, terminated = self.gather(torch.arange(self.ptr - n, self.ptr) % self.capacity)
        return obs, actions, next_obs, terminated

    def gather(self, idx):
        return tuple(t[idx] for t in self.tensors())

    def state_dict(self):
        return {"size": self.size, "ptr": self.ptr, "data": [t[:self.size].clone() for t in self.tensors()],
                "episode_returns": self.episode_returns[:self.size].clone(),
                "episode_starts": self.episode_starts[:self.size].clone(),
                "episode_lengths": self.episode_lengths[:self.size].clone()}

    def load_state_dict(self, state):
        self.size, self.ptr = state["size"], state["ptr"]
        for t, saved in zip(self.tensors(), state["data"]):
            t[:self.size] = saved
        for name in ("episode_returns", "episode_starts", "episode_lengths"):
            if name in state:  # checkpoints from before these were kept lack them
                getattr(self, name)[:self.size] = state[name]


class TeacherBuffer:
    """R_E: whole episodes with their episodic returns (paper, "Self-Adaptive Imitation Learning").

    Promotion rule (Algorithm 1): a finished episode whose episodic return is strictly higher
    than the threshold C = min return over the kept episodes joins the buffer whole.
    Capacity is in transitions (1e4 in the authors' released code). When a promotion overflows
    it, the lowest-return episodes leave first (never the one just added), so the buffer keeps
    the best episodes seen and the threshold never decreases. The authors' FIFO ring would
    instead drop the oldest data, which may be better than what stays.
    """

    def __init__(self, capacity):
        self.capacity = int(capacity)
        self.episodes = []  # (episodic_return, (obs, actions, next_obs, terminated))
        self._flat = None

    def __len__(self):
        return sum(len(ep[1][0]) for ep in self.episodes)

    @property
    def num_episodes(self):
        return len(self.episodes)

    @property
    def threshold(self):
        """C = min episodic return over the kept episodes (-inf when empty)."""
        return min((ret for ret, _ in self.episodes), default=-float("inf"))

    @property
    def returns(self):
        return [ret for ret, _ in self.episodes]

    def add_episode(self, episodic_return, obs, actions, next_obs, terminated):
        new = (float(episodic_return), tuple(torch.as_tensor(np.asarray(x), dtype=torch.float32)
                                             for x in (obs, actions, next_obs, terminated)))
        self.episodes.append(new)
        while len(self) > self.capacity and len(self.episodes) > 1:
            worst = min((ep for ep in self.episodes if ep is not new), key=lambda ep: ep[0])
            self.episodes.remove(worst)
        self._flat = [torch.cat(parts) for parts in zip(*(data for _, data in self.episodes))]
        self._flat_returns = torch.cat([torch.full((len(data[0]),), ret) for ret, data in self.episodes])
        self._flat_steps_left = torch.cat([torch.arange(len(data[0]) - 1, -1, -1) for _, data in self.episodes])

    def promote(self, episodic_return, obs, actions, next_obs, terminated):
        """Adds the episode if it beats the threshold; returns whether it did."""
        if episodic_return <= self.threshold:
            return False
        self.add_episode(episodic_return, obs, actions, next_obs, terminated)
        return True

    def sample(self, batch_size):
        """Uniform batch (obs, actions, next_obs, terminated) over the kept transitions."""
        idx = torch.randint(0, len(self._flat[0]), (batch_size,))
        return tuple(t[idx] for t in self._flat)

    def sample_steps(self, batch_size, n_step, with_returns=False):
        """As ReplayBuffer.sample_steps (without env rewards): runs of up to `n_step` consecutive
        transitions of one kept episode, the mask of those inside it, the episodic returns or None."""
        idx = torch.randint(0, len(self._flat[0]), (batch_size,))
        window, mask = step_window(idx, self._flat_steps_left[idx] if n_step > 1 else None, n_step, len(self._flat[0]))
        return tuple(t[window] for t in self._flat), mask, (self._flat_returns[idx] if with_returns else None)

    def state_dict(self):
        return {"capacity": self.capacity, "episodes": self.episodes}

    def load_state_dict(self, state):
        self.capacity, self.episodes = state["capacity"], []
        for ret, data in state["episodes"]:
            self.add_episode(ret, *data)


def load_teacher_buffer(path, env_id, env, num_demos, capacity, time_feature, absorbing):
    """R_E from the first `num_demos` episodes of a demo file, with the same observation
    features (time, absorbing state) that `env`'s wrappers add online, and without the
    contact forces that `env` drops (make_env's contact_forces=False)."""
    raw_obs_dim = env.observation_space.shape[0] - int(time_feature) - int(absorbing)
    file_obs_dim = raw_obs_dim + getattr(env, "dropped_obs_dims", 0)  # demo files keep the env's full observation
    teacher_buffer = TeacherBuffer(capacity)
    for episode in load_demos(path, env_id, file_obs_dim, env.action_space.shape[0], num_demos):
        for key in ("observations", "next_observations"):
            episode[key] = episode[key][:, :raw_obs_dim]  # the dropped entries are the last ones
        if len(episode["actions"]) > capacity:
            raise ConfigError(f"--teacher-capacity {capacity} is smaller than a demo episode")
        teacher_buffer.add_episode(episode["episodic_return"],
                                   *add_features(episode, env.max_episode_steps, time_feature, absorbing))
    return teacher_buffer


def step_window(first, steps_left, n_step, size):
    """Indices (len(first), n_step) of each transition in `first` and the n_step - 1 after it
    (modulo `size`), and a float mask that is 1 where that step is still in the first one's episode
    (`steps_left`: how many steps follow each first one there; not needed for one step)."""
    if n_step == 1:
        return first[:, None], torch.ones(len(first), 1)
    offsets = torch.arange(n_step)
    return (first[:, None] + offsets) % size, (offsets <= steps_left[:, None]).float()


def mixed_batch(teacher_buffer, self_buffer, batch_size, alpha, with_returns=False, n_step=1):
    """The mixture alpha * R_E + (1 - alpha) * R_B (paper, d_mix of Eq. qgrad/pigrad).

    round(alpha * batch_size) rows come from the teacher buffer and the rest from the self buffer;
    a row is a run of up to `n_step` consecutive steps of one episode (see `sample_steps`).
    Returns (obs, actions, next_obs, terminated) of shape (batch_size, n_step, ...), the env
    rewards of the self rows (teacher transitions carry no env reward: the learner never needs
    one), the mask of steps inside the episode and, with `with_returns`, the episodic return of
    each row's episode (else None).
    """
    num_teacher = round(alpha * batch_size)
    (obs, actions, rewards, next_obs, terminated), mask, returns = self_buffer.sample_steps(
        batch_size - num_teacher, n_step, with_returns)
    if num_teacher == 0:
        return (obs, actions, next_obs, terminated), rewards, mask, returns
    (t_obs, t_actions, t_next_obs, t_terminated), t_mask, t_returns = teacher_buffer.sample_steps(
        num_teacher, n_step, with_returns)
    batch = (torch.cat([t_obs, obs]), torch.cat([t_actions, actions]),
             torch.cat([t_next_obs, next_obs]), torch.cat([t_terminated, terminated]))
    return batch, rewards, torch.cat([t_mask, mask]), (torch.cat([t_returns, returns]) if with_returns else None)


# ---------------------------------------------------------------------------------------------
# Demo files
# ---------------------------------------------------------------------------------------------

def save_demos(path, episodes, env_id):
    """Writes a demo file atomically (temp file, then rename).

    `episodes` is a list of dicts as envs.rollout returns them: raw (feature-free) arrays
    observations, actions, next_observations, rewards (dense), the bools terminated / truncated
    for the episode, and its episodic_return.
    """
    lengths = np.array([len(ep["actions"]) for ep in episodes], dtype=np.int64)
    data = {
        "observations": np.concatenate([ep["observations"] for ep in episodes]).astype(np.float32),
        "actions": np.concatenate([ep["actions"] for ep in episodes]).astype(np.float32),
        "next_observations": np.concatenate([ep["next_observations"] for ep in episodes]).astype(np.float32),
        "rewards": np.concatenate([ep["rewards"] for ep in episodes]).astype(np.float32),
        "terminations": np.concatenate([_last_flag(n, ep["terminated"]) for n, ep in zip(lengths, episodes)]),
        "truncations": np.concatenate([_last_flag(n, ep["truncated"]) for n, ep in zip(lengths, episodes)]),
        "episode_lengths": lengths,
        "episode_returns": np.array([ep["episodic_return"] for ep in episodes], dtype=np.float64),
        "env_id": np.array(env_id),
        "gymnasium_version": np.array(_version("gymnasium")),
        "mujoco_version": np.array(_version("mujoco")),
    }
    atomic_write(path, lambda f: np.savez_compressed(f, **data))


def default_demo_path(env_id):
    """demos/<env>.npz beside this file: the shipped teacher demonstrations."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "demos", f"{env_id}.npz")


def load_demos(path, env_id, obs_dim, act_dim, num_demos=None):
    """Reads and checks demonstrations; returns a list of episode dicts (the first `num_demos`).

    `path` is a demo file (.npz, format in README.md) or a Minari dataset: its folder, or its
    id in the local Minari store (e.g. mujoco/hopper/medium-v0). Each episode: observations,
    actions, next_observations, rewards (raw float32 arrays), terminated (bool),
    episodic_return (float). Any problem raises ConfigError naming the source.
    """
    if os.path.isfile(path):
        try:
            with np.load(path, allow_pickle=False) as f:
                data = {k: f[k] for k in f.files}
        except Exception as e:  # not a zip, a damaged one (zlib), a plain .npy array, ...
            raise ConfigError(f"demo file {path} is not a readable .npz file ({first_line(e)})") from None
    elif os.path.isdir(path) or not path.endswith(".npz"):
        data = read_minari(path)
    else:
        raise ConfigError(f"demo file {path} not found (make one with make_demos.py --env {env_id})")
    missing = [k for k in DEMO_KEYS if k not in data]
    if missing:
        raise ConfigError(f"demo file {path} lacks {', '.join(missing)}")
    not_numbers = [k for k in DEMO_KEYS if k != "env_id" and (np.ndim(data[k]) == 0 or not (
        np.issubdtype(data[k].dtype, np.number) or data[k].dtype == bool))]
    if not_numbers:
        raise ConfigError(f"demo file {path}: {', '.join(not_numbers)} must be arrays of numbers")
    file_env = str(data["env_id"])
    n = len(data["actions"])
    if file_env != env_id:
        raise ConfigError(f"demo file {path} holds demonstrations for {file_env}, not {env_id}")
    if data["observations"].ndim != 2 or data["observations"].shape[1] != obs_dim:
        raise ConfigError(f"demo file {path}: observations have shape {data['observations'].shape}, "
                          f"{env_id} has {obs_dim}-dim observations")
    if data["actions"].ndim != 2 or data["actions"].shape[1] != act_dim:
        raise ConfigError(f"demo file {path}: actions have shape {data['actions'].shape}, "
                          f"{env_id} has {act_dim}-dim actions")
    lengths = data["episode_lengths"].astype(np.int64)
    same_rows = all(len(data[k]) == n for k in ("observations", "next_observations", "rewards",
                                                    "terminations", "truncations"))
    if not same_rows or lengths.sum() != n or (lengths <= 0).any() or len(data["episode_returns"]) != len(lengths):
        raise ConfigError(f"demo file {path} is inconsistent: arrays and episode_lengths disagree")
    if not all(np.isfinite(data[k]).all() for k in ("observations", "actions", "next_observations", "rewards",
                                                    "episode_returns")):
        raise ConfigError(f"demo file {path} holds NaN or inf values")
    num_demos = len(lengths) if num_demos is None else num_demos
    if num_demos > len(lengths):
        raise ConfigError(f"demo file {path} holds {len(lengths)} episodes, {num_demos} were asked for")
    episodes, start = [], 0
    for length, ret in zip(lengths[:num_demos], data["episode_returns"][:num_demos]):
        sl = slice(start, start + length)
        episodes.append({
            "observations": data["observations"][sl], "actions": data["actions"][sl],
            "next_observations": data["next_observations"][sl], "rewards": data["rewards"][sl],
            "terminated": bool(data["terminations"][sl][-1]), "episodic_return": float(ret),
        })
        start += length
    return episodes


def _minari():
    try:
        import minari
    except ImportError:
        raise ConfigError("Minari datasets need the minari package: pip install -r requirements-extras.txt") from None
    return minari


def read_minari(source):
    """A Minari dataset (folder, or id in the local store; nothing is downloaded) as the arrays of
    a demo file. Minari keeps N+1 observations for an episode of N actions: observation t and
    t+1 make transition t."""
    try:
        minari = _minari()
    except ConfigError as e:
        if os.path.isdir(source):
            raise
        raise ConfigError(f"{source} is not a demo file; as a Minari dataset id, it needs the minari package "
                          "(pip install -r requirements-extras.txt)") from None
    try:
        if os.path.isdir(source):
            data_dir = os.path.join(source, "data") if os.path.isdir(os.path.join(source, "data")) else source
            dataset = minari.MinariDataset(data_dir)
        else:
            dataset = minari.load_dataset(source)
        episodes = list(dataset.iterate_episodes())
    except Exception as e:
        where = "is a folder but not a Minari dataset" if os.path.isdir(source) else \
            "is neither a demo file nor a dataset in the local Minari store"
        raise ConfigError(f"{source} {where} ({first_line(e)})") from None
    if not episodes or not all(isinstance(ep.observations, np.ndarray) for ep in episodes):
        raise ConfigError(f"Minari dataset {source} has no episodes with flat array observations")
    cat = lambda parts, dtype: np.concatenate(parts).astype(dtype)  # noqa: E731
    return {
        "observations": cat([ep.observations[:-1] for ep in episodes], np.float32),
        "next_observations": cat([ep.observations[1:] for ep in episodes], np.float32),
        "actions": cat([ep.actions for ep in episodes], np.float32),
        "rewards": cat([ep.rewards for ep in episodes], np.float32),
        "terminations": cat([ep.terminations for ep in episodes], bool),
        "truncations": cat([ep.truncations for ep in episodes], bool),
        "episode_lengths": np.array([len(ep.actions) for ep in episodes], dtype=np.int64),
        "episode_returns": np.array([np.sum(ep.rewards, dtype=np.float64) for ep in episodes]),
        "env_id": np.array(dataset.env_spec.id if dataset.env_spec is not None else ""),
    }


def check_minari_id(dataset_id):
    """Before any training: ConfigError unless `dataset_id` has Minari's form and is new in the local store."""
    minari = _minari()
    from minari.dataset.minari_dataset import DATASET_ID_RE
    match = DATASET_ID_RE.fullmatch(dataset_id)
    if match is None or match.group("version") is None:
        raise ConfigError(f"--minari {dataset_id}: a Minari dataset id has the form [namespace/]name-vN, "
                          "e.g. sail/hopper/teacher-v0")
    if dataset_id in minari.list_local_datasets():
        raise ConfigError(f"the Minari dataset {dataset_id} exists already in the local store")


def save_minari(dataset_id, episodes, env_id):
    """Writes episodes (dicts as envs.rollout returns them) as a Minari dataset in the local store."""
    minari = _minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer
    buffers = [EpisodeBuffer(observations=np.concatenate([ep["observations"], ep["next_observations"][-1:]]),
                             actions=np.asarray(ep["actions"]), rewards=list(ep["rewards"]),
                             terminations=[False] * (len(ep["actions"]) - 1) + [ep["terminated"]],
                             truncations=[False] * (len(ep["actions"]) - 1) + [ep["truncated"]])
               for ep in episodes]
    try:
        with warnings.catch_warnings():  # minari asks for author, e-mail, code links: not known here
            warnings.simplefilter("ignore", UserWarning)
            return minari.create_dataset_from_buffers(
                dataset_id, buffers, env=env_id, eval_env=env_id, algorithm_name="make_demos.py (TD3 teacher)",
                description=f"{len(episodes)} episodes of a sub-optimal TD3 teacher on {env_id}, recorded by make_demos.py")
    except Exception as e:  # e.g. the id was taken meanwhile
        raise ConfigError(f"cannot write the Minari dataset {dataset_id}: {first_line(e)}") from None


def _last_flag(length, flag):
    flags = np.zeros(length, dtype=bool)
    flags[-1] = flag
    return flags


def _version(package):
    from importlib.metadata import version
    return version(package)
