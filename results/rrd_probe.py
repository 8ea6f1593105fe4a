"""The return-decomposition probe: how well the learned per-step reward matches the dense one.

    python results/rrd_probe.py RUN_DIR [--noise 0 0.1 0.5] [--seed 1234]

RUN_DIR is a sail.py run folder made with --return-decomposition > 0 (config.json and
checkpoint.pt). Plays one episode of its actor per noise level (Gaussian action noise, as
--exploration-noise) on a dense-reward copy of the env, and prints the episode's dense return
against the sum of the reward model's r(s, a, s') over the same steps, and their per-step
correlation. The learner never sees the dense reward; only this probe reads it.
"""

import argparse
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from envs import make_env  # noqa: E402
from plumbing import load_checkpoint  # noqa: E402
from sail import RewardModel  # noqa: E402
from td3 import TD3  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
p.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.1, 0.5], help="action noise std per episode")
p.add_argument("--seed", type=int, default=1234, help="seed of the probe's env and noise")
args = p.parse_args()
for name in ("config.json", "checkpoint.pt"):
    if not os.path.isfile(os.path.join(args.run_dir, name)):
        p.error(f"{args.run_dir} has no {name}: give a run folder made by sail.py")
config = json.load(open(os.path.join(args.run_dir, "config.json")))
if not config.get("return_decomposition"):
    p.error(f"{args.run_dir} was made without --return-decomposition: it has no reward model")
torch.set_num_threads(1)
torch.set_grad_enabled(False)
env = make_env(config["env"], args.seed, sparse=False, time_feature=config["time_feature"],
               absorbing=config["absorbing"],
               contact_forces=config.get("contact_forces", True))
obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
agent = TD3(obs_dim, act_dim, env.action_space.low, env.action_space.high, hidden=config["hidden"],
            critic_layer_norm=config.get("critic_layer_norm", False))
reward_model = RewardModel(obs_dim, act_dim, config["hidden"])
load_checkpoint(os.path.join(args.run_dir, "checkpoint.pt"), {"agent": agent, "reward_model": reward_model})
rng = np.random.default_rng(args.seed)

for noise in args.noise:
    obs, _ = env.reset()
    dense, learned, done = [], [], False
    while not done:
        action = agent.explore(obs, noise, rng) if noise > 0 else agent.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        learned.append(float(reward_model(*(torch.as_tensor(np.asarray(x, np.float32))[None]
                                              for x in (obs, action, next_obs)))))
        dense.append(float(reward))
        obs, done = next_obs, terminated or truncated
    dense, learned = np.array(dense), np.array(learned)
    print(f"noise {noise}: {len(dense)} steps, dense return {dense.sum():.1f}, sum of r {learned.sum():.1f}, "
          f"per-step correlation {np.corrcoef(dense, learned)[0, 1]:.2f}")
