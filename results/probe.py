"""The checkpoint probes: what D and the critic say.

    python results/probe.py RUN_DIR [--velocity-index 8]

RUN_DIR is a run folder with config.json and checkpoint.pt (the checkpoints stay with the runs,
outside the repo). Prints, for an --absorbing run (DAC): D's reward log D - log(1 - D) in the
absorbing state, and the critic's min(Q1, Q2) there with the zero action and with the actor's
action, against its mean over the last 20k states of the self buffer (with the actor's action).
For every run: the critic's Q1 at the actor's actions over up to 4096 states of the self buffer,
its mean magnitude, its mean slope |dQ1/da| per action dimension and their ratio, the pull per
unit on each action dimension of an actor's loss that divides Q by its magnitude (as TD3+BC's
does); and D's mean output on the recorded teacher episodes of the run's demo file with one
observation (by default 8, the forward velocity of HalfCheetah-v5) scaled by 0.75 to 1.5, then
with the teacher's actions scaled by 0 to 2 (clipped to the action bounds): how much D's reward
depends on the action at all. Last, over the last 100k transitions of the self buffer, in 8 equal
bins of observation --height-index (by default 0, the torso's height on Ant-v5, Hopper-v5 and
Walker2d-v5; 5 is Hopper-v5's forward velocity): how many there are, D's reward as the critic got it (--reward
sail or airl), the learned reward of --return-decomposition where the run has one and the critic's whole reward
(D's plus the learned one over its unit, as sail.py's update adds them; without a --return-bonus), the critic's
min(Q1, Q2) at the actions taken, and the squared action norm. Then what R_E holds: each kept episode's return, length and mean of
observation --velocity-index, the lowest return first; and its rewards, Q and observation --velocity-index by steps
to the end of their episode (1-10, 11-30, 31-60, 61-100, more), for the episodes that fell (ended by a termination)
and for those the time limit cut.
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from demos import default_demo_path, load_demos  # noqa: E402
from envs import absorbing_state, add_features  # noqa: E402
from run_folder import critic_reward, load_agent, load_parts  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--velocity-index", type=int, default=8, help="the observation scaled in the D probe")
p.add_argument("--height-index", type=int, default=0, help="the observation whose bins the last probe reports")
args = p.parse_args()
config, env, agent, state = load_agent(p, args.run_dir, seed=0)
actor, critic = agent.actor, agent.critic
obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
parts = load_parts(config, state, obs_dim, act_dim, ("disc", "reward_model", "self_buffer"))
disc, self_buffer = parts["disc"], parts["self_buffer"]  # R_B, a ring: once full, its newest steps are not its last
self_obs = state["self_buffer"]["data"][0]
sample = self_obs[torch.randperm(len(self_obs), generator=torch.Generator().manual_seed(0))[:4096]]
with torch.enable_grad():
    policy_actions = actor(sample).detach().requires_grad_(True)
    q = critic.q1(sample, policy_actions)
    slope, = torch.autograd.grad(q.sum(), policy_actions)
slope = (slope * actor.action_scale).abs().mean().item()  # per unit of half the action range, as the penalties
print(f"Q1 at the actor's actions ({len(sample)} states of R_B): mean |Q| {q.abs().mean().item():.1f}, mean slope "
      f"per action dimension {slope:.3f}, their ratio {slope / q.abs().mean().item():.4f}")

if config["absorbing"]:
    absorbing = torch.as_tensor(absorbing_state(obs_dim - 1))[None]
    zero = torch.zeros(1, act_dim)
    recent = self_buffer.latest(min(20_000, self_buffer.size))[0]
    print(f"D's reward in the absorbing state: {disc(disc.inputs(absorbing, zero)).item():.2f}")
    print(f"Q(absorbing, 0) {torch.min(*critic(absorbing, zero)).item():.1f}, "
          f"Q(absorbing, actor) {torch.min(*critic(absorbing, actor(absorbing))).item():.1f}, "
          f"mean Q(s, actor) over the last 20k states {torch.min(*critic(recent, actor(recent))).mean().item():.1f}")

demo_path = config["demos"] or default_demo_path(config["env"])
raw_obs_dim = obs_dim - int(config["time_feature"]) - int(config["absorbing"])
episodes = load_demos(demo_path, config["env"], raw_obs_dim, act_dim, config["num_demos"])
obs, actions = [], []
max_steps = env.max_episode_steps  # the time feature's denominator
for episode in episodes:
    o, a, *_ = add_features(episode, max_steps, config["time_feature"], config["absorbing"])
    keep = o[:, -1] != 1.0 if config["absorbing"] else slice(None)  # not the absorbing state
    obs.append(o[keep]), actions.append(a[keep])
obs, actions = torch.as_tensor(np.concatenate(obs)), torch.as_tensor(np.concatenate(actions))
for scale in (0.75, 1.0, 1.25, 1.5):
    scaled = obs.clone()
    scaled[:, args.velocity_index] *= scale
    print(f"D on the teacher's state-actions, observation {args.velocity_index} x {scale}: "
          f"{torch.sigmoid(disc(disc.inputs(scaled, actions))).mean().item():.2f}")
low, high = actor.action_bias - actor.action_scale, actor.action_bias + actor.action_scale
for scale in (0.0, 0.5, 1.0, 1.5, 2.0):
    scaled = (actor.action_bias + scale * (actions - actor.action_bias)).clamp(low, high)
    d = torch.sigmoid(disc(disc.inputs(obs, scaled))).mean().item()
    print(f"D on the teacher's states, actions x {scale}: {d:.3f}")

# Where in the state the rewards go: D's reward and the learned one, by bins of one observation entry
obs, actions, next_obs, _ = self_buffer.latest(min(100_000, self_buffer.size))
d_reward, _, reward_given = critic_reward(config, state, parts, obs, actions, next_obs, env.max_episode_steps)
learned = parts["reward_model"](obs, actions, next_obs) if "reward_model" in parts else None  # in returns per step
q_taken = torch.min(*critic(obs, actions))  # what the critic values the steps that were taken at
entry = obs[:, args.height_index].contiguous()
edges = torch.linspace(entry.min().item(), entry.max().item(), 9)
print(f"R_B's last {len(obs)} transitions by observation {args.height_index}:")
bins = torch.bucketize(entry, edges[1:-1], right=True)  # 0-7; the top edge falls in the last bin
for i, (low, high) in enumerate(zip(edges[:-1], edges[1:])):
    inside = bins == i
    if not inside.any():
        print(f"  {low:.2f} to {high:.2f}: none")
        continue
    print(f"  {low:.2f} to {high:.2f}: {int(inside.sum())} transitions, "
          + (f"D's reward {d_reward[inside].mean().item():.3f}, " if d_reward is not None else "")
          + (f"learned reward {learned[inside].mean().item():.3f}, critic's reward "
             f"{reward_given[inside].mean().item():.3f}, " if learned is not None else "")
          + f"Q {q_taken[inside].mean().item():.1f}, squared action norm {actions[inside].pow(2).sum(1).mean().item():.2f}")

# What R_E holds now: the demos and the promoted episodes that are left, the lowest return first
teacher_episodes = sorted(state["teacher_buffer"]["episodes"], key=lambda episode: episode[0])
print(f"R_E: {len(teacher_episodes)} episodes (return, steps, mean of observation {args.velocity_index}):")
for episodic_return, (episode_obs, *_) in teacher_episodes:
    print(f"  {episodic_return:.1f}, {len(episode_obs)}, {episode_obs[:, args.velocity_index].mean().item():.2f}")

# The steps into a fall: R_E's rewards and Q by steps to the end of their episode, for the episodes that ended by
# a termination and for those the time limit cut (where a fast gait falls, D may pay most for the last steps)
print("R_E by steps to its episode's end:")
for fell in (True, False):
    episodes = [data for _, data in teacher_episodes if (data[3][-1] > 0) == fell]
    if not episodes:
        print(f"  {'fell' if fell else 'ran to the time limit'}: no episode")
        continue
    obs, actions, next_obs = (torch.cat([data[i] for data in episodes]) for i in range(3))
    steps_to_end = torch.cat([torch.arange(len(data[0]), 0, -1) for data in episodes])
    d_reward, learned, _ = critic_reward(config, state, parts, obs, actions, next_obs, env.max_episode_steps)
    q_taken = torch.min(*critic(obs, actions))
    for first, last in ((1, 10), (11, 30), (31, 60), (61, 100), (101, None)):
        inside = (steps_to_end >= first) & (steps_to_end <= (last or len(steps_to_end)))
        if inside.any():
            print(f"  {'fell' if fell else 'ran to the time limit'}, {first}{f'-{last}' if last else ' or more'} steps "
                  f"to the end: {int(inside.sum())} transitions, "
                  + (f"D's reward {d_reward[inside].mean().item():.2f}, " if d_reward is not None else "")
                  + (f"learned {learned[inside].mean().item():.2f}, " if learned is not None else "")
                  + f"Q {q_taken[inside].mean().item():.1f}, observation {args.velocity_index} "
                  f"{obs[inside][:, args.velocity_index].mean().item():.2f}")
