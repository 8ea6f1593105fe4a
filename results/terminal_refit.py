"""Would a critic that fits R_B's terminal transitions see the actor's early end coming?

    python results/terminal_refit.py RUN_DIR [--share 0.1] [--updates 4000] [--seed 1000]

RUN_DIR is a sail.py run folder (config.json and checkpoint.pt). Plays one episode of the
deterministic actor, then prints the critic's min(Q1, Q2) along it (first, middle, tenth-last and
last step) and on R_B's terminal transitions (those of its last 100k transitions, and all), with
the reward the critic is given there (D's plus the learned one, as sail.py's update adds them; no
return bonus). Then refits the critic from the checkpoint twice, --updates TD3 steps each, the actor
and the target actor frozen, D and the reward model fixed: once on sail.py's batches, once with
--share of each batch replaced by R_B's terminal transitions, printing the same after each quarter.
Where oversampling brings Q on R_B's terminals down to their reward but not along the actor's own
episode, the states the actor ends in are not among R_B's.
"""

import argparse
import copy
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from buffers import mixed_batch  # noqa: E402
from envs import rollout  # noqa: E402
from plumbing import positive_int, unit_interval  # noqa: E402
from run_folder import critic_reward, load_agent, load_parts  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--share", type=unit_interval, default=0.1, help="share of a batch from terminal transitions")
p.add_argument("--updates", type=positive_int, default=4000, help="TD3 steps of each refit")
p.add_argument("--seed", type=int, default=1000, help="seed of the actor's episode and of the batches")
args = p.parse_args()
config, env, agent, checkpoint = load_agent(p, args.run_dir, args.seed)
if config["return_decomposition"] <= 0 or config["reward"] not in ("sail", "airl"):
    p.error(f"{args.run_dir}: a run with D's reward and a learned one (sail.py's defaults) is needed")
parts = load_parts(config, checkpoint, env.observation_space.shape[0], env.action_space.shape[0])
self_buffer, teacher_buffer = parts["self_buffer"], parts["teacher_buffer"]
loop = checkpoint["loop"]
episode = rollout(env, agent.act)
episode_obs = torch.as_tensor(episode["observations"], dtype=torch.float32)
episode_actions = agent.actor(episode_obs)
terminal = torch.nonzero(self_buffer.terminated[:self_buffer.size]).squeeze(-1)
if len(terminal) == 0:
    p.error(f"{args.run_dir}: R_B holds no terminal transition")
recent = terminal[terminal >= self_buffer.size - 100_000]
print(f"{config['env']} at step {loop['global_step']}: the actor's episode, return {episode['episodic_return']:.0f}, "
      f"{episode['length']} steps, {'terminated' if episode['terminated'] else 'truncated'}; "
      f"R_B's terminal transitions: {len(recent)} of its last 100000, {len(terminal)} in all")


def reward(obs, actions, next_obs):  # as sail.py's update adds them, without a return bonus
    return critic_reward(config, checkpoint, parts, obs, actions, next_obs, env.max_episode_steps)[2]


def report(label):
    q = torch.min(*agent.critic(episode_obs, episode_actions))
    marks = sorted({0, len(q) // 2, max(len(q) - 10, 0), len(q) - 1})
    line = f"{label}: the actor's episode, min(Q1, Q2) " + ", ".join(f"step {i + 1}: {q[i]:.1f}" for i in marks)
    for name, idx in (("recent", recent), ("all", terminal)):
        if len(idx):
            obs, actions, _, next_obs, _ = self_buffer.gather(idx)
            line += (f"; R_B's terminals ({name}): Q {torch.min(*agent.critic(obs, actions)).mean():.1f}, "
                     f"reward {reward(obs, actions, next_obs).mean():.2f}")
    print(line, flush=True)


report("checkpoint")
torch.set_grad_enabled(True)  # load_agent turned gradients off: the refits need them
start = copy.deepcopy(agent.state_dict())
for share in (0.0, args.share):
    agent.load_state_dict(copy.deepcopy(start))
    for group in agent.actor_optimizer.param_groups:
        group["lr"] = 0.0
    torch.manual_seed(args.seed)
    for i in range(1, args.updates + 1):
        (obs, actions, next_obs, terminated), _, _ = mixed_batch(teacher_buffer, self_buffer, config["batch_size"],
                                                                 loop["alpha"])
        k = round(share * len(obs))
        if k:
            obs[-k:], actions[-k:], _, next_obs[-k:], terminated[-k:] = self_buffer.gather(
                terminal[torch.randint(0, len(terminal), (k,))])
        with torch.no_grad():
            rewards = reward(obs, actions, next_obs)
        agent.update(obs, actions, rewards, next_obs, terminated)
        agent.actor_target.load_state_dict(start["actor_target"])  # Polyak would move it to the actor
        if i % max(args.updates // 4, 1) == 0 or i == args.updates:
            with torch.no_grad():
                report(f"share {share:g}, {i} updates")
