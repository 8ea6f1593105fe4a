"""The two buffers of SAIL: the self replay buffer R_B and the adaptive teacher buffer R_E.

Both hold float32 torch tensors (a 1e6-transition Walker2d buffer with the time feature is
about 0.15 GB) and sample with torch's global RNG, so a fixed torch seed fixes the batches.
R_E starts from a demo file (demos.py).
"""

import numpy as np
import torch

from plumbing import ConfigError


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

    def sample_finished(self, batch_size):
        """Uniform batch from the transitions whose episode has ended (the newest episode is still
        running), and the episodic return of each one's episode (for the return bonus)."""
        idx = self.finished_indices(batch_size)
        return self.gather(idx), self.episode_returns[idx]

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

    def sample_recent(self, batch_size, window):
        """Uniform batch from the `window` most recent transitions (the on-policy D's negatives)."""
        window = min(window, self.size)
        back = torch.randint(1, window + 1, (batch_size,))
        return self.gather((self.ptr - back) % self.capacity)

    def latest(self, n):
        """The n most recent transitions (obs, actions, next_obs, terminated), oldest first: the
        episode that just ended, for the teacher buffer."""
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

    keep="pareto" (sail.py's default) changes only which episode leaves first: the one that the most
    kept episodes beat on both the return and the return per step, the lowest return among those.
    Episodes of one length are then ranked by their return alone, as by keep="return"; where episodes
    end early, a short fast one (a teacher that runs, then falls) stays beside longer slow ones
    (standing still) until an episode both earns more and earns it faster.
    """

    def __init__(self, capacity, keep="return"):
        self.capacity, self.keep = int(capacity), keep
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
            self.episodes.remove(self._first_to_leave(new))
        self._flat = [torch.cat(parts) for parts in zip(*(data for _, data in self.episodes))]
        self._flat_returns = torch.cat([torch.full((len(data[0]),), ret) for ret, data in self.episodes])

    def _first_to_leave(self, new):
        others = [ep for ep in self.episodes if ep is not new]
        if self.keep == "return":
            return min(others, key=lambda ep: ep[0])
        def score(ep):  # the return and the return per step
            return ep[0], ep[0] / len(ep[1][0])
        scores = [score(ep) for ep in self.episodes]

        def beaten(ep):  # how many kept episodes have at least its return and rate, and more of one
            mine = score(ep)
            return sum(r >= mine[0] and q >= mine[1] and (r, q) != mine for r, q in scores)
        return min(others, key=lambda ep: (-beaten(ep), ep[0]))

    def promote(self, episodic_return, obs, actions, next_obs, terminated):
        """Adds the episode if it beats the threshold; returns whether it did."""
        if episodic_return <= self.threshold:
            return False
        self.add_episode(episodic_return, obs, actions, next_obs, terminated)
        return True

    def sample(self, batch_size):
        """Uniform batch (obs, actions, next_obs, terminated, episodic return of each one's episode)
        over the kept transitions."""
        idx = torch.randint(0, len(self._flat[0]), (batch_size,))
        return (*(t[idx] for t in self._flat), self._flat_returns[idx])

    def state_dict(self):
        return {"capacity": self.capacity, "episodes": self.episodes}

    def load_state_dict(self, state):
        self.capacity, self.episodes = state["capacity"], []
        for ret, data in state["episodes"]:
            self.add_episode(ret, *data)


def mixed_batch(teacher_buffer, self_buffer, batch_size, alpha, with_returns=False):
    """The mixture alpha * R_E + (1 - alpha) * R_B (the paper's d_mix of Eqs. 7 and 8).

    round(alpha * batch_size) rows come from the teacher buffer and the rest from the self buffer.
    Returns (obs, actions, next_obs, terminated), the env rewards of the self rows (teacher
    transitions carry no env reward: the learner never needs one) and, with `with_returns`, the
    episodic return of each row's episode (self rows then come from finished episodes only), else None.
    """
    num_teacher = round(alpha * batch_size)
    if with_returns:
        (obs, actions, rewards, next_obs, terminated), returns = self_buffer.sample_finished(batch_size - num_teacher)
    else:
        (obs, actions, rewards, next_obs, terminated), returns = self_buffer.sample(batch_size - num_teacher), None
    if num_teacher == 0:
        return (obs, actions, next_obs, terminated), rewards, returns
    t_obs, t_actions, t_next_obs, t_terminated, t_returns = teacher_buffer.sample(num_teacher)
    batch = (torch.cat([t_obs, obs]), torch.cat([t_actions, actions]),
             torch.cat([t_next_obs, next_obs]), torch.cat([t_terminated, terminated]))
    return batch, rewards, (torch.cat([t_returns, returns]) if with_returns else None)
