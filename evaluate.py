"""Saved actors: model.pt, and playing a run's actor back (`sail.py --evaluate RUN_DIR`).

sail.py and bc.py write model.pt with --save-model; every sail.py run also keeps its actor in
checkpoint.pt. `evaluate_run` rebuilds the env and the actor from the run's config.json and
plays episodes with the deterministic policy, printing the dense return of each.
"""

import os

import numpy as np
import torch

import plumbing
from envs import make_env, rollout
from plumbing import ConfigError
from td3 import TD3


def save_model(run_dir, agent, disc, args):
    """model.pt: actor, critics and discriminator (None for BC), with what rebuilds the actor."""
    model = {"actor": agent.actor, "critic": agent.critic}
    if disc is not None:
        model["discriminator"] = disc
    plumbing.save_checkpoint(os.path.join(run_dir, "model.pt"), model, env=args.env, hidden=args.hidden,
                             time_feature=args.time_feature, absorbing=args.absorbing)


def evaluate_run(run_dir, episodes, seed, threads):
    """Plays `episodes` episodes of RUN_DIR's saved actor (model.pt, else checkpoint.pt) on an env
    seeded with `seed`; prints the return and length of each, then their mean."""
    path = next((p for p in (os.path.join(run_dir, n) for n in ("model.pt", "checkpoint.pt")) if os.path.isfile(p)),
                None)
    if path is None or not os.path.isfile(os.path.join(run_dir, "config.json")):
        raise ConfigError(f"--evaluate {run_dir}: no config.json with model.pt or checkpoint.pt there")
    config = plumbing.read_config(run_dir)
    saved = plumbing.load_checkpoint(path, map_location="cpu")  # also a run made with --device cuda
    torch.set_num_threads(threads)
    try:
        env = make_env(config.env, seed, time_feature=config.time_feature, absorbing=config.absorbing)
    except AttributeError as e:
        raise ConfigError(f"{run_dir}/config.json lacks {e.name}: not a run folder of sail.py or bc.py") from None
    agent = TD3(env.observation_space.shape[0], env.action_space.shape[0], env.action_space.low,
                env.action_space.high, hidden=config.hidden)
    try:
        agent.actor.load_state_dict(saved["actor"] if "actor" in saved else saved["agent"]["actor"])
    except (RuntimeError, KeyError, TypeError) as e:  # config.json and the saved networks disagree (sizes, env)
        raise ConfigError(f"{path} does not fit {run_dir}/config.json: {plumbing.first_line(e)}") from None
    returns = []
    for i in range(episodes):
        episode = rollout(env, agent.act)
        returns.append(episode["episodic_return"])
        print(f"episode {i + 1}: return {returns[-1]:.1f}, length {len(episode['actions'])}")
    print(f"{config.env}, {path}: mean return {np.mean(returns):.1f} +- {np.std(returns):.1f} "
          f"over {len(returns)} episodes (env seed {seed})")
    return 0
