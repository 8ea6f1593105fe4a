"""What the checkpoint probes of results/ share: a sail.py run folder's env, TD3 agent and other parts, loaded,
and the reward its critic was given."""

import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from buffers import ReplayBuffer, TeacherBuffer  # noqa: E402
from credit import RewardModel, decomposition_unit  # noqa: E402
from discriminator import Discriminator, shaped_reward  # noqa: E402
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


def load_parts(config, checkpoint, obs_dim, act_dim, names=("disc", "reward_model", "self_buffer", "teacher_buffer")):
    """Of the checkpoint's D, reward model, R_B and R_E, those named, each built as sail.py builds it and loaded;
    a part the checkpoint does not hold (the reward model of a run without --return-decomposition) is left out."""
    # the learned action cost: --action-cost reward or reward-and-actor (before it was one flag: its older name)
    learns_action_cost = config.get("action_cost", "none") != "none" or config.get("decomposition_action_cost", False)
    builders = {
        "disc": lambda: Discriminator(obs_dim, act_dim, config["disc_hidden"], config.get("disc_action_norm", False)),
        "reward_model": lambda: RewardModel(obs_dim, act_dim, config["hidden"], learns_action_cost),
        "self_buffer": lambda: ReplayBuffer(obs_dim, act_dim, config["buffer_size"]),
        "teacher_buffer": lambda: TeacherBuffer(config["teacher_capacity"], config.get("teacher_keep", "return"))}
    parts = {}
    for name in names:
        if checkpoint.get(name) is not None:
            parts[name] = builders[name]()
            parts[name].load_state_dict(checkpoint[name])
    return parts


def critic_reward(config, checkpoint, parts, obs, actions, next_obs, episode_steps):
    """The reward sail.py's update gives the critic, without the return bonus: D's reward (None for a run
    without D's: TD3-sparse, IRCR, RRD), the learned one weighted and over its unit (None for a run without
    one), and their sum."""
    d = shaped_reward(parts["disc"], obs, actions, config["reward"]) if config["reward"] in ("sail", "airl") else None
    learned = None
    if "reward_model" in parts:
        loop = checkpoint["loop"]
        unit = decomposition_unit(config.get("decomposition_unit", "range"), loop["return_range"], loop["rate_range"],
                                  episode_steps)
        learned = config["return_decomposition"] * parts["reward_model"](obs, actions, next_obs) / unit
    return d, learned, (0.0 if d is None else d) + (0.0 if learned is None else learned)
