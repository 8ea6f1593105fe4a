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
observation --velocity-index, the lowest return first.
"""

import argparse
import os
import sys

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from buffers import ReplayBuffer  # noqa: E402
from credit import RewardModel, decomposition_unit  # noqa: E402
from demos import default_demo_path, load_demos  # noqa: E402
from discriminator import Discriminator, shaped_reward  # noqa: E402
from envs import absorbing_state, add_features  # noqa: E402
from plumbing import run_folder_checkpoint, run_folder_config  # noqa: E402
from td3 import Actor, TwinCritic  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--velocity-index", type=int, default=8, help="the observation scaled in the D probe")
p.add_argument("--height-index", type=int, default=0, help="the observation whose bins the last probe reports")
args = p.parse_args()
config = run_folder_config(p, args.run_dir)
state = run_folder_checkpoint(p, args.run_dir)
self_obs = state["self_buffer"]["data"][0]
obs_dim, act_dim = self_obs.shape[1], state["self_buffer"]["data"][1].shape[1]
self_buffer = ReplayBuffer(obs_dim, act_dim, config["buffer_size"])
self_buffer.load_state_dict(state["self_buffer"])  # a ring: once full, its newest steps are not its last rows
disc = Discriminator(obs_dim, act_dim, config["disc_hidden"], config.get("disc_action_norm", False))
disc.load_state_dict(state["disc"])
critic = TwinCritic(obs_dim, act_dim, config["hidden"], config.get("critic_layer_norm", False))
critic.load_state_dict(state["agent"]["critic"])
actor = Actor(obs_dim, act_dim, config["hidden"], -np.ones(act_dim), np.ones(act_dim))
actor.load_state_dict(state["agent"]["actor"])  # its buffers hold the env's action bounds
sample = self_obs[torch.randperm(len(self_obs), generator=torch.Generator().manual_seed(0))[:4096]]
policy_actions = actor(sample).detach().requires_grad_(True)
q = critic.q1(sample, policy_actions)
slope, = torch.autograd.grad(q.sum(), policy_actions)
slope = (slope * actor.action_scale).abs().mean().item()  # per unit of half the action range, as the penalties
print(f"Q1 at the actor's actions ({len(sample)} states of R_B): mean |Q| {q.abs().mean().item():.1f}, mean slope "
      f"per action dimension {slope:.3f}, their ratio {slope / q.abs().mean().item():.4f}")
torch.set_grad_enabled(False)

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
max_steps = gym.spec(config["env"]).max_episode_steps or 1000  # the time feature's denominator, as in envs.make_env
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
d_reward = shaped_reward(disc, obs, actions, config["reward"]) if config["reward"] in ("sail", "airl") else None
learned = None
if state.get("reward_model") is not None:
    # the learned action cost: --action-cost reward or reward-and-actor (before it was one flag: its older name)
    learn_action_cost = config.get("action_cost", "none") != "none" or config.get("decomposition_action_cost", False)
    reward_model = RewardModel(obs_dim, act_dim, config["hidden"], learn_action_cost)
    reward_model.load_state_dict(state["reward_model"])
    learned = reward_model(obs, actions, next_obs)
    unit = decomposition_unit(config.get("decomposition_unit", "range"), state["loop"]["return_range"],
                              state["loop"]["rate_range"], gym.spec(config["env"]).max_episode_steps or 1000)
    # the reward the critic is given, as sail.py's update makes it (D's, or none, plus the learned one in its unit)
    critic_reward = (d_reward if d_reward is not None else 0.0) + config["return_decomposition"] * learned / unit
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
             f"{critic_reward[inside].mean().item():.3f}, " if learned is not None else "")
          + f"Q {q_taken[inside].mean().item():.1f}, squared action norm {actions[inside].pow(2).sum(1).mean().item():.2f}")

# What R_E holds now: the demos and the promoted episodes that are left, the lowest return first
teacher_episodes = sorted(state["teacher_buffer"]["episodes"], key=lambda episode: episode[0])
print(f"R_E: {len(teacher_episodes)} episodes (return, steps, mean of observation {args.velocity_index}):")
for episodic_return, (episode_obs, *_) in teacher_episodes:
    print(f"  {episodic_return:.1f}, {len(episode_obs)}, {episode_obs[:, args.velocity_index].mean().item():.2f}")
