"""Trains a sub-optimal TD3 teacher on the dense reward and records its demonstrations.

    python make_demos.py --env Hopper-v5

The teacher is plain TD3 (td3.py) on the dense MuJoCo reward. Every --eval-freq steps its
deterministic policy is evaluated; once the mean return lies in the target band, episodes are
recorded and those whose return is also in the band are kept. With --num-episodes of them the
demo file is written (atomically) and the script ends. The band defaults follow the teacher
quality of the paper's released code (github.com/illidanlab/SAIL: Hopper ~1480, Walker2d ~1675,
HalfCheetah ~5650, Swimmer ~121, Ant ~1130), clearly below what TD3 reaches with dense rewards.

The demo file goes to demos/<env>.npz beside this script (where sail.py looks for it); an
existing file is only replaced with --force. Ctrl-C or SIGTERM stops the teacher cleanly after
a checkpoint (with --checkpoint), which a later run with the same flags continues (a checkpoint
written with other flags is refused).
"""

import os
import sys

import plumbing

if __name__ == "__main__":
    plumbing.quiet_interrupt_while_importing("make_demos.py")

import time

import numpy as np
import torch

from buffers import ReplayBuffer
from demos import check_minari_id, default_demo_path, save_demos, save_minari
from envs import EnvState, make_env, rollout
from plumbing import ConfigError
from td3 import TD3

# teacher return bands (low, high) at the paper's teacher quality, except Ant-v5: there an Ant that
# stands still scores about 980 (a healthy reward of 1 per step), so the paper's ~1130 admits
# teachers that barely walk; from 1200 up the teacher walks forward
BANDS = {
    "Hopper-v5": (1000, 1500),
    "Walker2d-v5": (1000, 1700),
    "HalfCheetah-v5": (4000, 6000),
    "Swimmer-v5": (40, 120),
    "Ant-v5": (1200, 1800),
}
# flags a run continued from --checkpoint may give anew: where its outputs go, and its threads
RESUMABLE = ("output", "force", "save_teacher", "minari", "checkpoint", "checkpoint_freq", "threads")


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Hopper-v5", help="gymnasium env id")
    p.add_argument("--seed", type=plumbing.seed, default=0, help="seed of env, action space and torch")
    p.add_argument("--band", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="teacher return band (default: the paper's quality for the five envs)")
    p.add_argument("--num-episodes", type=plumbing.positive_int, default=10, help="episodes to record")
    p.add_argument("--output", help="demo file (default: demos/<env>.npz beside this script)")
    p.add_argument("--force", action="store_true", help="replace an existing demo file")
    p.add_argument("--save-teacher", metavar="DIR", help="also keep the teacher as a run folder (config.json, "
                   "model.pt) that `evaluate.py DIR` plays back")
    p.add_argument("--minari", metavar="DATASET_ID", help="also write the episodes as this Minari dataset in the "
                   "local Minari store (e.g. sail/hopper/teacher-v0; needs the extras)")
    p.add_argument("--total-timesteps", type=plumbing.positive_int, default=1_000_000,
                   help="give up if the band is not reached after this many env steps")
    p.add_argument("--learning-starts", type=int, default=10_000, help="uniformly random steps first")
    p.add_argument("--eval-freq", type=plumbing.positive_int, default=5_000, help="env steps between evaluations")
    p.add_argument("--eval-episodes", type=plumbing.positive_int, default=5, help="episodes per evaluation")
    p.add_argument("--record-attempts", type=plumbing.positive_int, default=40,
                   help="episodes tried per recording round to find --num-episodes in the band")
    p.add_argument("--exploration-noise", type=plumbing.non_negative_float, default=0.1,
                   help="std of Gaussian action noise")
    p.add_argument("--batch-size", type=plumbing.positive_int, default=256, help="TD3 batch size")
    p.add_argument("--hidden", type=plumbing.positive_int, nargs="+", default=[128, 128],
                   help="hidden layer sizes (small: a mediocre teacher needs no more, and trains 3x faster)")
    p.add_argument("--lr", type=plumbing.non_negative_float, default=3e-4,
                   help="Adam learning rate of actor and critic")
    p.add_argument("--gamma", type=float, default=0.99, help="discount")
    p.add_argument("--threads", type=plumbing.threads, default=1, help="torch CPU threads")
    p.add_argument("--checkpoint", help="checkpoint file, written every --checkpoint-freq steps and "
                   "resumed from if it exists (default: none)")
    p.add_argument("--checkpoint-freq", type=plumbing.positive_int, default=25_000, help="env steps between checkpoints")
    args = p.parse_args(argv)
    if args.band is None:
        if args.env not in BANDS:
            try:
                make_env(args.env, 0)
            except ConfigError as e:
                p.error(str(e))
            p.error(f"no default band for {args.env}: give --band LOW HIGH")
        args.band = BANDS[args.env]
    if not args.band[0] < args.band[1]:  # also nan
        p.error(f"--band needs LOW < HIGH, got {args.band[0]} {args.band[1]}")
    if not 0.0 < args.gamma <= 1.0:
        p.error(f"--gamma must be in (0, 1], got {args.gamma}")
    if args.learning_starts < 0:
        p.error("--learning-starts must be >= 0")
    args.output = args.output or default_demo_path(args.env)
    return args


def record_in_band(eval_env, agent, in_band, args):
    """Deterministic episodes of the teacher, at most --record-attempts: those in the band, up to --num-episodes."""
    episodes = []
    for _ in range(args.record_attempts):
        episode = rollout(eval_env, agent.act)
        if in_band(episode["episodic_return"]):
            episodes.append(episode)
            if len(episodes) == args.num_episodes:
                break
    return episodes


def write_outputs(args, agent, episodes, global_step):
    save_demos(args.output, episodes, args.env)
    if args.minari:
        save_minari(args.minari, episodes, args.env)
        print(f"wrote the Minari dataset {args.minari}")
    if args.save_teacher:
        args.algo, args.time_feature, args.absorbing = "teacher", False, False
        teacher_dir = plumbing.make_run_dir(os.path.dirname(os.path.abspath(args.save_teacher)),
                                            os.path.basename(os.path.abspath(args.save_teacher)),
                                            vars(args) | {"script": "make_demos.py"})
        plumbing.save_model(teacher_dir, agent, None, args)
        print(f"wrote the teacher to {teacher_dir}")
    rets = [ep["episodic_return"] for ep in episodes]
    lens = [len(ep["actions"]) for ep in episodes]
    print(f"wrote {args.output}: {len(episodes)} episodes after {global_step} teacher steps, "
          f"returns {np.mean(rets):.1f} +- {np.std(rets):.1f} (min {min(rets):.1f}, "
          f"max {max(rets):.1f}), lengths {min(lens)}-{max(lens)}")


def train(args):
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    # The teacher sees raw observations and the dense reward; demos are stored raw.
    env = make_env(args.env, args.seed, sparse=False, time_feature=False)
    eval_env = make_env(args.env, args.seed + 10_000, sparse=False, time_feature=False)
    if os.path.exists(args.output) and not args.force:
        raise ConfigError(f"{args.output} exists; give --force to replace it, or another --output")
    for path in filter(None, (args.output, args.checkpoint)):  # found now, not after an hour of training
        plumbing.check_writable(path)
    if args.save_teacher and os.path.exists(args.save_teacher):
        raise ConfigError(f"--save-teacher {args.save_teacher} exists already")
    if args.save_teacher:
        plumbing.check_writable(os.path.join(args.save_teacher, "model.pt"))
        os.rmdir(args.save_teacher)  # made by the check: the folder is written only with the teacher in it
    if args.minari:
        check_minari_id(args.minari)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    low, high = env.action_space.low, env.action_space.high
    agent = TD3(obs_dim, act_dim, low, high, hidden=args.hidden, lr=args.lr, gamma=args.gamma)
    buffer = ReplayBuffer(obs_dim, act_dim, min(args.total_timesteps, 1_000_000))
    band_low, band_high = args.band
    in_band = lambda ret: band_low <= ret <= band_high  # noqa: E731

    obs, _ = env.reset()
    first_step = 1
    parts = {"agent": agent, "buffer": buffer, "env": EnvState(env), "eval_env": EnvState(eval_env),
             "rng": plumbing.RNGs(rng)}
    # what the teacher's training depends on; the rest says where outputs go, or how fast it runs
    flags = {k: list(v) if isinstance(v, tuple) else v for k, v in vars(args).items() if k not in RESUMABLE}

    def same_flags(state):
        """Before the parts are loaded: another run's networks and buffer may not even fit this run's."""
        saved = state.get("flags", flags)  # older checkpoints lack them
        changed = [k for k in saved if flags.get(k) != saved[k]]
        if changed:
            raise ConfigError(f"--checkpoint {args.checkpoint} was written with other flags ("
                              + ", ".join(f"{plumbing.as_flag(k, saved[k])}, not {plumbing.as_flag(k, flags.get(k))}"
                                          for k in changed) + "): give the same flags, or another --checkpoint")

    if args.checkpoint and os.path.isfile(args.checkpoint):
        state = plumbing.load_checkpoint(args.checkpoint, parts, check=same_flags)
        obs, first_step = state["obs"], state["global_step"] + 1
        print(f"resumed from {args.checkpoint} at step {state['global_step']}", flush=True)

    def save_checkpoint(global_step):
        plumbing.save_checkpoint(args.checkpoint, parts, obs=obs, global_step=global_step, flags=flags)

    start = time.time()
    with plumbing.StopRequest() as stop:
        print(f"training the teacher on {args.env}, steps {first_step} to {args.total_timesteps}", flush=True)
        for global_step in range(first_step, args.total_timesteps + 1):
            if stop.requested:
                if args.checkpoint:
                    save_checkpoint(global_step - 1)
                    print(f"stopped at step {global_step - 1}; the same command continues from {args.checkpoint}")
                else:
                    print(f"stopped at step {global_step - 1} (no --checkpoint: nothing kept)")
                return stop.exit_code
            if global_step <= args.learning_starts:
                action = env.action_space.sample()
            else:
                action = agent.explore(obs, args.exploration_noise, rng)
            next_obs, reward, terminated, truncated, info = env.step(action)
            buffer.add(obs, action, reward, next_obs, terminated)
            obs = next_obs
            if terminated or truncated:
                obs, _ = env.reset()

            if global_step > args.learning_starts:
                obs_b, act_b, rew_b, next_obs_b, term_b = buffer.sample(args.batch_size)
                agent.update(obs_b, act_b, rew_b, next_obs_b, term_b)

            if global_step % args.eval_freq == 0 and global_step > args.learning_starts:  # a trained teacher only
                returns = [rollout(eval_env, agent.act)["episodic_return"] for _ in range(args.eval_episodes)]
                mean = float(np.mean(returns))
                print(f"step {global_step}: teacher eval return {mean:.1f} +- {np.std(returns):.1f} "
                      f"({(global_step - first_step + 1) / (time.time() - start):.0f} steps/s)", flush=True)
                if in_band(mean):
                    episodes = record_in_band(eval_env, agent, in_band, args)
                    if len(episodes) == args.num_episodes:
                        write_outputs(args, agent, episodes, global_step)
                        return 0
                    print(f"  only {len(episodes)} of {args.record_attempts} episodes in the band; training on")

            # after the evaluation and recording, which draw on eval_env: a resumed run replays neither
            if args.checkpoint and global_step % args.checkpoint_freq == 0:
                save_checkpoint(global_step)
    raise ConfigError(f"the teacher did not reach the band {args.band} within {args.total_timesteps} steps")


def main(argv=None):
    return plumbing.run_main("make_demos.py", train, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
