"""Behaviour cloning, the paper's simplest baseline: regress the teacher's actions.

    python bc.py --env Hopper-v5

The TD3 actor of td3.py learns the teacher's action for each teacher state (mean squared error)
for --bc-steps gradient steps, without any env interaction, and is evaluated on the dense
episodic return every --eval-freq gradient steps. The run folder has the layout of sail.py's
(config.json, progress.csv with the same columns, model.pt), so plot.py and
`evaluate.py RUN_DIR` read it as any other run.
"""

import sys

import plumbing

if __name__ == "__main__":
    plumbing.quiet_interrupt_while_importing("bc.py")

import argparse

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from demos import default_demo_path, load_teacher_buffer
from envs import evaluate_policy, make_env
from plumbing import PROGRESS_COLUMNS, ConfigError
from td3 import TD3, make_adam


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Walker2d-v5", help="gymnasium env id")
    p.add_argument("--seed", type=plumbing.seed, default=1, help="seed of the eval env, numpy and torch")
    p.add_argument("--demos", help="demo file (default: demos/<env>.npz)")
    p.add_argument("--num-demos", type=plumbing.positive_int, default=1, help="teacher episodes used from the demo file")
    p.add_argument("--bc-steps", type=plumbing.positive_int, default=20_000, help="gradient steps")
    p.add_argument("--batch-size", type=plumbing.positive_int, default=256, help="teacher transitions per gradient step")
    p.add_argument("--lr", type=plumbing.non_negative_float, default=3e-4, help="Adam learning rate")
    p.add_argument("--hidden", type=plumbing.positive_int, nargs="+", default=[256, 256], help="actor hidden sizes")
    p.add_argument("--time-feature", action=argparse.BooleanOptionalAction, default=True,
                   help="append 1 - t/T to obs (as SAIL's actor sees it)")
    p.add_argument("--eval-freq", type=plumbing.positive_int, default=10_000, help="gradient steps between evaluations")
    p.add_argument("--eval-episodes", type=plumbing.positive_int, default=5, help="episodes per evaluation")
    p.add_argument("--threads", type=plumbing.threads, default=2, help="torch CPU threads")
    p.add_argument("--output-dir", default="runs", help="parent folder of the run folder")
    p.add_argument("--run-name", help="run folder name (default: <env>__bc__<seed>__<time>)")
    p.add_argument("--tensorboard", action="store_true", help="also log progress.csv's numbers to TensorBoard")
    args = p.parse_args(argv)
    plumbing.check_tensorboard(p, args)
    args.algo, args.method, args.absorbing = "bc", "BC", False  # what plot.py and evaluate.py read from config.json
    return args


def train(args):
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    eval_env = make_env(args.env, args.seed + 100, time_feature=args.time_feature)
    obs_dim, act_dim = eval_env.observation_space.shape[0], eval_env.action_space.shape[0]
    teacher_buffer = load_teacher_buffer(args.demos or default_demo_path(args.env), args.env, eval_env, args.num_demos,
                                         10**9, args.time_feature, absorbing=False)
    agent = TD3(obs_dim, act_dim, eval_env.action_space.low, eval_env.action_space.high, hidden=args.hidden)
    optimizer = make_adam(agent.actor.parameters(), args.lr)
    run_dir = plumbing.make_run_dir(args.output_dir, args.run_name or plumbing.run_name(args.env, "bc", args.seed),
                                    vars(args) | {"script": "bc.py"})
    print(f"run folder: {run_dir}", flush=True)

    log = plumbing.ProgressLog(run_dir, PROGRESS_COLUMNS, [], args.tensorboard)
    for step in tqdm(range(1, args.bc_steps + 1), desc=f"bc {args.env}", unit="update", mininterval=1.0):
        obs, actions, *_ = teacher_buffer.sample(args.batch_size)
        loss = F.mse_loss(agent.actor(obs), actions)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % args.eval_freq == 0 or step == args.bc_steps:
            if not np.isfinite(loss.item()):
                raise ConfigError(f"BC loss is {loss.item()} at step {step}")
            evaluation = evaluate_policy(eval_env, agent.act, args.eval_episodes)
            log.append({k: float("nan") for k in PROGRESS_COLUMNS} | evaluation | {
                "global_step": 0, "updates": step, "teacher_threshold": teacher_buffer.threshold,
                "teacher_episodes": teacher_buffer.num_episodes, "alpha": 1.0, "actor_loss": loss.item()})
    plumbing.save_model(run_dir, agent, None, args)
    return 0


if __name__ == "__main__":
    sys.exit(plumbing.run_main("bc.py", train, parse_args()))
