"""What the checkpoint probes of results/ share: a sail.py run folder's env and TD3 agent, loaded."""

import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from envs import make_env  # noqa: E402
from plumbing import run_folder_checkpoint, run_folder_config  # noqa: E402
from td3 import TD3  # noqa: E402


def load_agent(parser, run_dir, seed):
    """RUN_DIR's config (a dict), an env made as the run's (seeded with `seed`), its TD3 agent with the
    checkpoint's networks, and the whole checkpoint; a folder that is not a run is the parser's one error line.
    One thread, no gradients: a probe only reads."""
    config = run_folder_config(parser, run_dir)
    torch.set_num_threads(1)
    torch.set_grad_enabled(False)
    env = make_env(config["env"], seed, time_feature=config["time_feature"], absorbing=config["absorbing"])
    agent = TD3(env.observation_space.shape[0], env.action_space.shape[0], env.action_space.low, env.action_space.high,
                hidden=config["hidden"], gamma=config["gamma"], tau=config["tau"], policy_noise=config["policy_noise"],
                noise_clip=config["noise_clip"], policy_delay=config["policy_delay"],
                critic_layer_norm=config.get("critic_layer_norm", False))
    checkpoint = run_folder_checkpoint(parser, run_dir, {"agent": agent})
    return config, env, agent, checkpoint
