"""The actor's drift: how far the actor is from its Polyak-averaged target, and what the critic says about it.

    python results/actor_drift.py RUN_DIR [--episodes 3] [--seed 1000] [--critic-search N] [--critic-check N]

RUN_DIR is a sail.py run folder (config.json and checkpoint.pt). Plays --episodes episodes of the
deterministic target actor and prints their returns and lengths; then, on their states, the mean
|actor(s) - target(s)| per action entry (in units of half the action range), the share of action
entries at the bounds (|tanh| > 0.99) of each, and the critic's min(Q1, Q2) at the actor's and at
the target's actions: where the two agree, the critic is flat between the two actions. Then one
episode of the actor itself: how it ended, the critic's min(Q1, Q2) at its actions at the first,
middle, tenth-last and last step (whether the critic sees an early end coming), and the first two
entries of the observation at its last step (Hopper-v5 and Walker2d-v5: the torso's height and
angle). Last, the median over parameters of Adam's |m| / sqrt(v) for the actor and the critics:
about 0.15 where a gradient is zero-mean noise of a steady size (the stationary std of m with
beta1 = 0.9 is sqrt(0.1 / 1.9) of the gradient's; less where the size varies), near 1 where it
keeps its sign. Adam's step is lr times that ratio, whatever the gradient's size. With --critic-search N,
last, N episodes of the critic's own policy: at each step, of the actor's action and 64 perturbations of it
(Gaussian, std 0.2 half ranges, clipped to the bounds), the one with the highest min(Q1, Q2): where the actor
falls, whether the critic knows a way out nearby. With --critic-check N, N episodes of the actor, each with the
critic's min(Q1, Q2) at its actions over its first 50 steps against what followed them: the discounted sum of the
reward sail.py's update would give the critic for the rest of the episode (from the checkpoint's D, learned reward
and return bonus; at the time limit the critic's own value of the last state): where Q is the larger, the critic
values the actor's walk above what it earns; then both per episode (whether Q, at an episode's start, tells the
episodes that fall from those that run).
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from credit import return_bonus  # noqa: E402
from envs import rollout  # noqa: E402
from plumbing import positive_int  # noqa: E402
from run_folder import critic_reward, load_agent, load_parts  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--episodes", type=positive_int, default=3, help="episodes of the target actor")
p.add_argument("--seed", type=int, default=1000, help="seed of the probe's env")
p.add_argument("--critic-search", type=positive_int, default=None, metavar="N",
               help="episodes of the policy that takes the critic's best of 65 actions near the actor's")
p.add_argument("--critic-check", type=positive_int, default=None, metavar="N",
               help="episodes of the actor with the critic's Q against the discounted reward that followed")
args = p.parse_args()
config, env, agent, checkpoint = load_agent(p, args.run_dir, args.seed)

episodes = [rollout(env, lambda obs: agent.act(obs, target=True)) for _ in range(args.episodes)]
print(f"{config['env']} at step {checkpoint['loop']['global_step']}: the target actor's episodes, returns "
      + ", ".join(f"{e['episodic_return']:.0f}" for e in episodes) + "; lengths "
      + ", ".join(str(e["length"]) for e in episodes))
states = torch.as_tensor(np.concatenate([e["observations"] for e in episodes]), dtype=torch.float32)
scale, bias = agent.actor.action_scale, agent.actor.action_bias
actions, target_actions = agent.actor(states), agent.actor_target(states)
at_bounds = [(((a - bias) / scale).abs() > 0.99).float().mean() for a in (actions, target_actions)]
print(f"on their {len(states)} states: mean |actor - target| per action entry "
      f"{((actions - target_actions) / scale).abs().mean():.3f} (half ranges); at the bounds: actor "
      f"{at_bounds[0]:.3f}, target {at_bounds[1]:.3f}")
q_actor, q_target = (torch.min(*agent.critic(states, a)) for a in (actions, target_actions))
print(f"critic's min(Q1, Q2): at the actor's actions {q_actor.mean():.1f}, at the target's {q_target.mean():.1f}, "
      f"mean |difference| {(q_actor - q_target).abs().mean():.2f}")
# the actor's own episode: does the critic see its end coming?
episode = rollout(env, agent.act)
states = torch.as_tensor(episode["observations"], dtype=torch.float32)
q = torch.min(*agent.critic(states, agent.actor(states)))
marks = sorted({0, len(q) // 2, max(len(q) - 10, 0), len(q) - 1})
print(f"the actor's episode: return {episode['episodic_return']:.0f}, {episode['length']} steps, "
      f"{'terminated' if episode['terminated'] else 'truncated'}; min(Q1, Q2) at its actions, "
      + ", ".join(f"step {i + 1}: {q[i]:.1f}" for i in marks)
      + "; the observation at its last step, first entries "
      + ", ".join(f"{x:.3f}" for x in episode["observations"][-1][:2]))
for name in ("actor_optimizer", "critic_optimizer"):
    state = checkpoint["agent"][name]["state"].values()
    ratio = torch.cat([(s["exp_avg"].abs() / (s["exp_avg_sq"].sqrt() + 1e-8)).flatten() for s in state])
    print(f"{name.split('_')[0]}'s Adam: median |m| / sqrt(v) {ratio.median():.3f}")
if args.critic_search:
    generator = torch.Generator().manual_seed(args.seed)
    low, high = (torch.as_tensor(bound, dtype=torch.float32) for bound in (env.action_space.low, env.action_space.high))

    def critics_choice(obs):
        state = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        action = agent.actor(state)
        noise = 0.2 * scale * torch.randn(64, action.shape[1], generator=generator)
        candidates = torch.cat([action, action + noise]).clamp(low, high)
        return candidates[torch.min(*agent.critic(state.expand(len(candidates), -1), candidates)).argmax()].numpy()
    episodes = [rollout(env, critics_choice) for _ in range(args.critic_search)]
    print(f"the critic's own policy (its best of the actor's action and 64 perturbed ones): returns "
          + ", ".join(f"{e['episodic_return']:.0f}" for e in episodes) + "; lengths "
          + ", ".join(str(e["length"]) for e in episodes) + f"; {sum(e['terminated'] for e in episodes)} of "
          f"{len(episodes)} ended early")
if args.critic_check:
    parts = load_parts(config, checkpoint, *(space.shape[0] for space in (env.observation_space, env.action_space)),
                       names=("disc", "reward_model"))
    checks = []
    for _ in range(args.critic_check):
        episode = rollout(env, agent.act)
        obs, actions, next_obs = (torch.as_tensor(episode[key], dtype=torch.float32)
                                  for key in ("observations", "actions", "next_observations"))
        if config["reward"] == "env":  # TD3-sparse: the episodic return on the last step
            reward = torch.zeros(len(obs))
            reward[-1] = episode["episodic_return"]
        else:
            d_and_learned = critic_reward(config, checkpoint, parts, obs, actions, next_obs, env.max_episode_steps)[2]
            reward = torch.zeros(len(obs)) + torch.as_tensor(d_and_learned).flatten() + config["return_bonus"] * (
                return_bonus(torch.full((len(obs),), episode["episodic_return"]), checkpoint["loop"]["return_range"]))
        last = next_obs[-1:]
        value = 0.0 if episode["terminated"] else torch.min(*agent.critic(last, agent.actor(last))).item()
        followed = []
        for r in reversed(reward.tolist()):
            value = r + config["gamma"] * value
            followed.append(value)
        steps = min(50, len(obs))
        checks.append((episode, torch.min(*agent.critic(obs[:steps], actions[:steps])).mean().item(),
                       np.mean(followed[::-1][:steps])))
    q, followed = (np.mean([check[i] for check in checks]) for i in (1, 2))
    print(f"the actor's {len(checks)} episodes (returns " + ", ".join(f"{c[0]['episodic_return']:.0f}" for c in checks)
          + f"; {sum(c[0]['terminated'] for c in checks)} ended early): over their first 50 steps the critic's "
          f"min(Q1, Q2) {q:.1f}, the discounted reward that followed {followed:.1f}"
          + (f" ({100 * (q / followed - 1):+.0f}%)" if followed > 0 else ""))
    # the same per episode: does the critic tell, at an episode's start, the episodes that fall from those that run?
    print("  per episode, over its first 50 steps: min(Q1, Q2) " + ", ".join(f"{c[1]:.1f}" for c in checks)
          + "; the discounted reward that followed " + ", ".join(f"{c[2]:.1f}" for c in checks))
