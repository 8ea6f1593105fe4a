"""The return-decomposition probe: how well the learned per-step reward matches the dense one.

    python results/rrd_probe.py RUN_DIR [--noise 0 0.1 0.5] [--seed 1234] [--refit 16 64 256] [--refit-steps N]
                                        [--refit-hidden 64 64] [--refit-action-cost]

RUN_DIR is a sail.py run folder made with --return-decomposition > 0 (config.json and
checkpoint.pt). Plays one episode of its actor per noise level (Gaussian action noise, as
--exploration-noise) on a dense-reward copy of the env, and prints the episode's dense return
against the sum of the reward model's r(s, a, s') over the same steps, their per-step correlation
and the slope of r's least-squares line against the dense reward (r per unit of dense reward: 1
where r moves as the env's reward does, 0 where it is flat), and what the dense reward itself would
pay in RRD's loss for varying within the episode: the variance of the mean of K random steps of T,
(1 - K/T) Var / K, for the run's K and each --refit K (a reward flat within each episode pays 0).
Then, on the steps of the first of those episodes, how the learned reward moves when the actions
are scaled by 0 to 1.5 (clipped to the action bounds; s and s' kept) against how the env's control
cost moves (its weight times the squared action norm, gymnasium's v5 locomotion envs): whether the
model learned what actions cost.
The learner never sees the dense reward; only this probe reads it.

--refit K [K ...] trains, for each subset size K, a fresh reward model on the run's self buffer
R_B as sail.py does (`--decomposition-subset K`, --refit-steps minibatches; the run's hidden sizes
or --refit-hidden's), and prints the same action scaling over R_B's most recent 20k transitions
(their own s, a, s'): whether a smaller or larger subset learns more of what actions cost from the
same episodes; then the refit model's per-step correlation and slope against the dense reward on
the episodes played above. A run made with the learned action cost (--action-cost reward or
reward-and-actor; or any run, with --refit-action-cost) refits with it, and both report the
learned weight c.
"""

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from buffers import ReplayBuffer  # noqa: E402
from envs import make_env  # noqa: E402
from credit import RewardModel, train_reward_model  # noqa: E402
from plumbing import positive_int, run_folder_checkpoint, run_folder_config  # noqa: E402
from td3 import TD3, make_adam  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.1, 0.5], help="action noise std per episode")
p.add_argument("--seed", type=int, default=1234, help="seed of the probe's env and noise")
p.add_argument("--refit", type=int, nargs="*", default=[], metavar="K",
               help="subset sizes to train fresh reward models with on the run's R_B (one at least the episode "
               "length fits whole episodes, one per minibatch)")
p.add_argument("--refit-steps", type=int, default=5000, help="minibatches of each refit")
p.add_argument("--refit-hidden", type=positive_int, nargs="+", metavar="H", help="hidden sizes of the refit models "
               "(default: the run's)")
p.add_argument("--refit-action-cost", action="store_true", help="refit with the learned quadratic action cost "
               "(sail.py's --action-cost) whether or not the run had it")
args = p.parse_args()
config = run_folder_config(p, args.run_dir)
if not config.get("return_decomposition"):
    p.error(f"{args.run_dir} was made without --return-decomposition: it has no reward model")
if any(k < 1 for k in args.refit) or args.refit_steps < 1:
    p.error("--refit sizes must be at least 1, --refit-steps too")
torch.set_num_threads(1)
torch.set_grad_enabled(False)
env = make_env(config["env"], args.seed, sparse=False, time_feature=config["time_feature"],
               absorbing=config["absorbing"])
obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
agent = TD3(obs_dim, act_dim, env.action_space.low, env.action_space.high, hidden=config["hidden"],
            critic_layer_norm=config.get("critic_layer_norm", False))
# the learned action cost: --action-cost reward or reward-and-actor (before it was one flag: its older name)
learn_action_cost = config.get("action_cost", "none") != "none" or config.get("decomposition_action_cost", False)
reward_model = RewardModel(obs_dim, act_dim, config["hidden"], learn_action_cost)
self_buffer = ReplayBuffer(obs_dim, act_dim, config["buffer_size"])
run_folder_checkpoint(p, args.run_dir,
                      {"agent": agent, "reward_model": reward_model, "self_buffer": self_buffer})
rng = np.random.default_rng(args.seed)
low, high = (torch.as_tensor(x, dtype=torch.float32) for x in (env.action_space.low, env.action_space.high))
ctrl_cost_weight = getattr(env.unwrapped, "_ctrl_cost_weight", float("nan"))


def agreement(model, steps, dense):
    """The model's r on an episode's (s, a, s'), its per-step correlation with the dense reward and the slope
    of r's least-squares line against it."""
    r = model(*steps).reshape(-1).numpy()
    return r, np.corrcoef(dense, r)[0, 1], np.polyfit(dense, r, 1)[0]


def variance_term(rewards, subset):
    """The variance of the mean of `subset` of an episode's steps drawn without replacement: RRD's loss is the
    whole-episode fit plus this, so a reward flat within each episode pays nothing where the dense one pays it."""
    steps, subset = len(rewards), min(subset, len(rewards))
    return (1 - subset / steps) * np.var(rewards, ddof=1) / subset if steps > 1 else 0.0


played = []  # per noise level: the episode's (s, a, s') as tensors and its dense rewards
for noise in args.noise:
    obs, _ = env.reset()
    dense, steps, done = [], [], False
    while not done:
        action = agent.explore(obs, noise, rng) if noise > 0 else agent.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        dense.append(float(reward))
        steps.append((obs, action, next_obs))
        obs, done = next_obs, terminated or truncated
    played.append(([torch.as_tensor(np.array(x), dtype=torch.float32) for x in zip(*steps)], np.array(dense)))
    learned, correlation, slope = agreement(reward_model, *played[-1])
    variance_terms = ", ".join(f"K = {k} {variance_term(np.array(dense), k):.3g}"
                               for k in sorted({config["decomposition_subset"], *args.refit}))
    print(f"noise {noise}: {len(dense)} steps, dense return {sum(dense):.1f}, sum of r {learned.sum():.1f}, "
          f"per-step correlation {correlation:.2f}, slope {slope:.2f}; "
          f"the dense reward's variance term {variance_terms}")


def print_action_scaling(model, obs, actions, next_obs):
    base_reward = model(obs, actions, next_obs).mean()
    base_cost = actions.pow(2).sum(1).mean()
    for scale in (0.0, 0.5, 1.0, 1.5):
        scaled = torch.maximum(torch.minimum(scale * actions, high), low)
        change = float(model(obs, scaled, next_obs).mean() - base_reward)
        cost_change = ctrl_cost_weight * float(scaled.pow(2).sum(1).mean() - base_cost)
        print(f"actions x {scale}: mean r {change:+.3g} a step, the env's control cost {cost_change:+.3g} a step")


if learn_action_cost:
    print(f"learned action cost c = {float(reward_model.action_cost()):.4g} per unit of squared action norm "
          f"(the env's control cost weight: {ctrl_cost_weight:.4g})")
print_action_scaling(reward_model, *played[0][0])
refit_hidden = args.refit_hidden or config["hidden"]
recent = (self_buffer.ptr - torch.arange(1, min(20000, self_buffer.size) + 1)) % self_buffer.capacity
for subset in args.refit:
    torch.manual_seed(args.seed)
    model = RewardModel(obs_dim, act_dim, refit_hidden, learn_action_cost or args.refit_action_cost)
    optimizer = make_adam(model.parameter_groups(config["lr"]), config["lr"])
    losses = []
    with torch.enable_grad():
        for _ in range(args.refit_steps):
            losses.append(train_reward_model(model, optimizer, self_buffer, config["batch_size"], subset)
                          ["decomposition_loss"])
    last = torch.stack(losses[-1000:])
    learned_cost = f", c = {float(model.action_cost()):.4g}" if model.action_cost_rho is not None else ""
    print(f"refit with subsets of {subset} steps, hidden {refit_hidden}, "
          f"{args.refit_steps} minibatches (mean loss of the last {len(last)}: {float(last.mean()):.4g}"
          f"{learned_cost}), on R_B's last {len(recent)} transitions:")
    print_action_scaling(model, self_buffer.obs[recent], self_buffer.actions[recent], self_buffer.next_obs[recent])
    fits = [(noise, *agreement(model, *episode)[1:]) for noise, episode in zip(args.noise, played)]
    print("per-step correlation with the dense reward and slope: " + ", ".join(
        f"noise {noise} {correlation:.2f} {slope:.2f}" for noise, correlation, slope in fits))
