"""The early-end probe: which of a run's evaluation episodes end before the time limit, and how.

    python results/early_ends.py RUN_DIR [--episodes 20] [--seed 1000] [--target] [--rest-when-upside-down] [--zero-start N]
        [--time-left X]

RUN_DIR is a sail.py run folder (config.json and checkpoint.pt). Plays --episodes episodes of
its deterministic actor (--target: its Polyak-averaged target actor) and prints, for each, the
return and two of its dense parts, the forward reward (the distance covered over the step time)
and the control cost (the squared actions times the env's weight), the length and the range of
the first observation entry, which on Ant-v5, Hopper-v5 and
Walker2d-v5 is the torso's height (their observations leave out the x position), and on Ant-v5
the steps its torso spent upside down (entries 1-4 are the torso's orientation quaternion w, x,
y, z: the body's up axis points down where 1 - 2(x^2 + y^2) < 0); then the height range over
the run's teacher episodes, and the squared action norm per step of actor, teacher and R_E's episodes at
the checkpoint (in brackets: over the first 20 steps of each episode), which the
env's dense reward charges as control cost (Ant-v5: 0.5 a step per unit). Gymnasium's locomotion envs end an episode early when the body leaves
its healthy range (Ant-v5: a torso height outside [0.2, 1.0]; lying upside down is inside it).
An episode ended early if it is shorter than the time limit (with DAC's absorbing states, one step
longer than the fall; the absorbing state is left out of the ranges). Last, the run's own training
episodes (those in its replay buffer R_B, played with exploration noise), per --window env steps:
how many ended early, their lengths and the mean return (on Ant-v5 also how many had the ant upside
down, and their mean return); and whether the critic sees an early end coming: its min(Q1, Q2) at
R_B's actions over the last 100k transitions, by steps to a termination, against the episodes that
ran to the limit, with the squared action norm there. On Ant-v5 also the parts of the critic's
reward (D's reward, the return bonus, the learned reward of --return-decomposition in the critic's
unit) and its min(Q1, Q2) at the actor's actions and at the zero action, by steps to the first step upside down in R_B's
last 100k transitions; and with --rest-when-upside-down the probe's actor acts as trained until the
ant is upside down and then takes the zero action: what a turned-over episode would score if the
actor did not go on spending actions there; with --zero-start N it takes the zero action for each
episode's first N steps (whether the early ends come from how the actor starts); with --time-left X the
actor sees the time feature 1 - t/T as X at every step (whether its falls depend on the time left).
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from credit import return_bonus  # noqa: E402
from demos import default_demo_path  # noqa: E402
from envs import rollout  # noqa: E402
from plumbing import positive_int  # noqa: E402
from run_folder import critic_reward, load_agent, load_parts  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--episodes", type=positive_int, default=20, help="episodes to play")
p.add_argument("--seed", type=int, default=1000, help="seed of the probe's env")
p.add_argument("--target", action="store_true", help="play the target actor instead of the actor")
p.add_argument("--window", type=positive_int, default=50_000, help="env steps per line of the training episodes' summary")
p.add_argument("--rest-when-upside-down", action="store_true",
               help="Ant-v5: the zero action from the first step upside down to the episode's end")
p.add_argument("--zero-start", type=int, default=0, metavar="N", help="the zero action for each episode's first N steps")
p.add_argument("--time-left", type=float, metavar="X", help="the actor sees the time feature 1 - t/T as X at every step")
p.add_argument("--noise", type=float, default=0.0, metavar="X",
               help="the actor with training's Gaussian action noise (std X half action ranges): the episodes that "
                    "R_E's promotions come from")
args = p.parse_args()
if args.noise < 0 or (args.noise and args.target):
    p.error("--noise takes X >= 0 and plays the actor as training does (not with --target)")
config, env, agent, checkpoint = load_agent(p, args.run_dir, args.seed)
noise_rng = np.random.default_rng(args.seed)
policy = ((lambda o: agent.act(o, target=True)) if args.target else
          (lambda o: agent.explore(o, args.noise, noise_rng)) if args.noise else agent.act)

unwrapped = env.unwrapped
ant = config["env"].startswith("Ant")
if args.rest_when_upside_down and not ant:
    p.error("--rest-when-upside-down is for Ant-v5 runs")
if args.time_left is not None and (not config["time_feature"] or config["absorbing"]):
    p.error("--time-left is for runs with the time feature (their observation's last entry) and no absorbing states")


def upside_down(states):
    """Ant-v5: entries 1-4 are the torso's orientation quaternion w, x, y, z; its up axis points
    down where 1 - 2(x^2 + y^2) < 0."""
    return 1 - 2 * (states[:, 2] ** 2 + states[:, 3] ** 2) < 0


# the env's control cost per step is its weight times the squared action norm (gymnasium's v5 locomotion envs)
weight = getattr(unwrapped, "_ctrl_cost_weight", float("nan"))
returns, early, action_cost, start_cost = [], 0, [], []
for i in range(args.episodes):
    positions = []  # the body's x position as each action is chosen

    turned = [False]

    def policy_noting_x(obs):
        positions.append(float(unwrapped.data.qpos[0]))
        if len(positions) <= args.zero_start:
            return np.zeros(env.action_space.shape, env.action_space.dtype)
        if args.rest_when_upside_down:
            turned[0] = turned[0] or bool(upside_down(obs[None])[0])
            if turned[0]:
                return np.zeros(env.action_space.shape, env.action_space.dtype)
        if args.time_left is not None:
            obs = np.concatenate([obs[:-1], np.array([args.time_left], obs.dtype)])
        return policy(obs)

    episode = rollout(env, policy_noting_x)
    # the dense reward's forward part sums x velocity x its weight: the distance covered over the step time
    forward = (unwrapped.data.qpos[0] - positions[0]) / unwrapped.dt * getattr(unwrapped, "_forward_reward_weight", 1.0)
    states = np.concatenate([episode["observations"], episode["next_observations"][-1:]])
    if config["absorbing"]:  # DAC's absorbing state (indicator 1) follows an early end: not a body state
        states = states[states[:, -1] == 0.0]
    height = states[:, 0]
    ended_early = episode["length"] < env.max_episode_steps
    returns.append(episode["episodic_return"])
    action_cost.append((episode["actions"] ** 2).sum(-1).mean())
    start_cost.append((episode["actions"][:20] ** 2).sum(-1).mean())
    early += ended_early
    ending = f"ended early, first entry {height[-1]:.2f} at the end" if ended_early else "ran to the limit"
    if ant:
        ending += f", {int(upside_down(states).sum())} steps upside down"
    print(f"episode {i + 1}: return {returns[-1]:.1f} (forward reward {forward:.0f}, control cost "
          f"{weight * (episode['actions'] ** 2).sum():.0f}), length {episode['length']}, first entry "
          f"{height.min():.2f}-{height.max():.2f}, {ending}")
print(f"{config['env']}, {'target actor' if args.target else 'actor'}"
      f"{' (the zero action once upside down)' if args.rest_when_upside_down else ''}"
      f"{f' (the zero action for the first {args.zero_start} steps)' if args.zero_start else ''}"
      f"{f' (seeing the time feature as {args.time_left})' if args.time_left is not None else ''}"
      f"{f' (with exploration noise {args.noise})' if args.noise else ''}: mean return {np.mean(returns):.1f} over "
      f"{args.episodes} episodes, {early} ended early (env seed {args.seed})")
with np.load(config.get("demos") or default_demo_path(config["env"]), allow_pickle=False) as demos:
    ends = np.cumsum(demos["episode_lengths"])[:config["num_demos"]]
    first = demos["observations"][:ends[-1], 0]
    print(f"teacher ({config['num_demos']} episodes): first entry {first.min():.2f}-{first.max():.2f}, "
          f"lengths {', '.join(str(n) for n in demos['episode_lengths'][:config['num_demos']])}")
    squared = (demos["actions"][:ends[-1]] ** 2).sum(-1)
    teacher_cost = squared.mean()
    teacher_start = np.mean([squared[end - n:end - n + 20].mean() for end, n in zip(ends, demos["episode_lengths"])])
# R_E's episodes at the end of the run (the teacher's that are left and the promoted ones): how hard they start
kept = [np.asarray(data[1]) ** 2 for _, data in checkpoint["teacher_buffer"]["episodes"]]
print(f"squared action norm per step: actor {np.mean(action_cost):.3f} ({np.mean(start_cost):.3f} in the first 20 "
      f"steps), teacher {teacher_cost:.3f} ({teacher_start:.3f}), R_E's {len(kept)} episodes "
      f"{np.mean([a.sum(-1).mean() for a in kept]):.3f} ({np.mean([a[:20].sum(-1).mean() for a in kept]):.3f}); control cost "
      f"weight {weight}: {weight * np.mean(action_cost) * env.max_episode_steps:.0f} against "
      f"{weight * teacher_cost * env.max_episode_steps:.0f} over {env.max_episode_steps} steps")

# every transition of R_B carries its episode's start (its index in R_B), length and return (NaN: unfinished)
self_buffer = checkpoint["self_buffer"]
if "episode_starts" not in self_buffer:
    print("training episodes: not kept in this checkpoint (R_B predates episode bounds: sail.py before 2026-11-24)")
    sys.exit(0)
starts, first = np.unique(self_buffer["episode_starts"].numpy(), return_index=True)
lengths, episode_returns = self_buffer["episode_lengths"].numpy()[first], self_buffer["episode_returns"].numpy()[first]
if ant:  # steps upside down per episode, by its start
    steps_flipped = np.bincount(self_buffer["episode_starts"].numpy(), weights=upside_down(self_buffer["data"][0].numpy()),
                                minlength=len(self_buffer["data"][0]))[starts]
print(f"training episodes (R_B, exploration noise {config['exploration_noise']}), by the R_B index they started at:")
for start in range(0, int(starts.max()) + 1, args.window):
    window = (starts >= start) & (starts < start + args.window) & ~np.isnan(episode_returns)
    if not window.any():
        continue
    short = np.sort(lengths[window & (lengths < env.max_episode_steps)])
    listed = f" (lengths {', '.join(map(str, short[:10]))}{', ...' if len(short) > 10 else ''})" if len(short) else ""
    flipped = ""
    if ant:
        turned = window & (steps_flipped > 0)
        flipped = f"; {turned.sum()} with the ant upside down" + (
            f" (their mean return {episode_returns[turned].mean():.1f})" if turned.any() else "")
    print(f"  {start}-{start + args.window}: {window.sum()} episodes, {len(short)} ended early{listed}, "
          f"mean return {episode_returns[window].mean():.1f}{flipped}")

# Does the critic see an early end coming? Its min(Q1, Q2) at R_B's own actions over the last 100k
# transitions, by steps to the end of episodes that ended in a termination (where the TD target is r
# alone), against the episodes that ran to the limit; with the squared action there (DAC's runs end
# in the absorbing state, never a termination: none to show)
obs, actions, terminated = (self_buffer["data"][i] for i in (0, 1, 4))
n = len(obs)
index = np.arange(n)
episode_start, episode_length = self_buffer["episode_starts"].numpy(), self_buffer["episode_lengths"].numpy()
last = (episode_start + episode_length - 1) % n  # R_B is a ring
to_end = (last - index) % n
finished = ~np.isnan(self_buffer["episode_returns"].numpy()) & (index >= n - 100_000)
ended = finished & (terminated.numpy()[last] == 1)
print(f"the critic's min(Q1, Q2) at R_B's actions (last {min(n, 100_000)} transitions), by steps to a termination:")
groups = [(f"{low}-{high}" if low else "0 (the terminal step)", ended & (to_end >= low) & (to_end <= high))
          for low, high in ((0, 0), (1, 3), (4, 10), (11, 30), (31, 100))]
groups.append(("episodes that ran to the limit", finished & ~ended))
for name, selected in groups:
    rows = np.flatnonzero(selected)
    if len(rows) == 0:
        print(f"  {name}: none")
        continue
    count, rows = len(rows), torch.as_tensor(np.random.default_rng(0).choice(rows, min(len(rows), 2000), replace=False))
    q = torch.min(*agent.critic(obs[rows].to(agent.device), actions[rows].to(agent.device)))
    print(f"  {name}: {count} transitions, mean over {len(rows)}: Q {q.mean().item():.1f}, "
          f"squared action norm {actions[rows].pow(2).sum(1).mean().item():.2f}")

if not ant:
    sys.exit(0)
# Ant-v5: what the critic's reward and Q say on the way to a flip and after it (R_B's last 100k
# transitions, by steps to the first step upside down of their episode), the reward as sail.py's
# update makes it from the checkpoint's D, reward model and ranges
flipped_now = upside_down(obs.numpy())
# each episode's first step upside down (R_B's index; -1 for none), by its start (R_B does not wrap in 300k steps)
first_by_start = np.full(n, n)
np.minimum.at(first_by_start, episode_start[flipped_now & finished], index[flipped_now & finished])
first_flip = np.where(first_by_start[episode_start] < n, first_by_start[episode_start], -1)
d_reward, learned, _ = critic_reward(config, checkpoint, load_parts(config, checkpoint, obs.shape[1], actions.shape[1],
                                                                    ("disc", "reward_model")),
                                     obs, actions, self_buffer["data"][3], env.max_episode_steps)
bonus = (config["return_bonus"] * return_bonus(self_buffer["episode_returns"], checkpoint["loop"]["return_range"])
         if config["return_bonus"] > 0 else None)
parts = {name: value for name, value in (("D's reward", d_reward), ("return bonus", bonus), ("learned reward", learned))
         if value is not None}
to_flip = np.where(first_flip >= 0, first_flip - index, np.iinfo(np.int64).max)
print(f"the critic's reward and min(Q1, Q2) at the actor's actions (R_B's last {min(n, 100_000)} transitions), "
      "by steps to the first step upside down:")
groups = [("episodes never upside down", finished & (first_flip < 0)),
          *((name, finished & (to_flip >= low) & (to_flip <= high)) for name, low, high in (
              ("over 100 steps before", 101, n), ("31-100 steps before", 31, 100), ("11-30 steps before", 11, 30),
              ("1-10 steps before", 1, 10))),
          ("upside down", finished & flipped_now),
          ("upright again after a flip", finished & (first_flip >= 0) & (to_flip < 0) & ~flipped_now)]
for name, selected in groups:
    rows = np.flatnonzero(selected)
    if len(rows) == 0:
        print(f"  {name}: none")
        continue
    rows_t = torch.as_tensor(rows)
    with torch.no_grad():
        o = obs[rows_t].to(agent.device)
        q = torch.min(*agent.critic(o, agent.actor(o)))
        q_zero = torch.min(*agent.critic(o, torch.zeros_like(actions[rows_t])))  # how much Q cares about the action
    print(f"  {name}: {len(rows)} transitions, " + "".join(f"{k} {v[rows_t].mean().item():.3f}, " for k, v in parts.items())
          + f"Q {q.mean().item():.2f} (at the zero action {q_zero.mean().item():.2f}), squared action norm "
          f"{actions[rows_t].pow(2).sum(1).mean().item():.2f}")
