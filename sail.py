"""SAIL: Self-Adaptive Imitation Learning (Zhu, Lin, Dai, Zhou), in one file.

    python sail.py --env Walker2d-v5

The environment returns no per-step reward, only the episodic return r_e when an episode ends
(envs.py). The agent starts from one to four episodes of a sub-optimal teacher (demos/<env>.npz).
Algorithm 1 of the paper, as the loop in `train` runs it:

    input: teacher buffer R_E (the demos), self buffer R_B (random-policy steps), alpha = 0.5
    for each env step:
        act with the TD3 actor plus Gaussian noise; R_B <- R_B + (s, a, s')
        if an episode tau just ended and r_e(tau) > min over R_E of r_e:  R_E <- R_E + tau,
            and alpha -> 0 (the adaptive teacher buffer and the dynamic alpha)
        every --disc-freq steps, train the discriminator D by Eq. (4): R_E labelled 1, R_B 0
        update the critic by Eq. (7) and the actor by Eq. (8), on batches drawn from
            alpha R_E + (1 - alpha) R_B, with the reward r'(s, a) = -log(1 - D(s, a))

The paper's ablations are flags (--fixed-alpha, --alpha 0, --no-adaptation, --disc-negatives recent);
DAC, TD3 on the sparse reward, IRCR and RRD are presets (--algo); `--algo sail-paper` is the paper's SAIL
exactly. The defaults add seven things, each a flag, each using only what the sparse env gives at episode ends:
- return bonus (--return-bonus, credit.py): r' + the episode's scaled return (step 4);
- return decomposition (--return-decomposition, credit.py): r' + a learned per-step reward (step 4);
- learned action cost (--action-cost): c ||a||^2 in that reward and in the actor's loss (step 4);
- LayerNorm in the critics (--critic-layer-norm, td3.py);
- on-policy D after the first promotion (--disc-negatives): recent steps are D's negatives (step 3);
- D's actions normalised as its states (--disc-action-norm, discriminator.py);
- Pareto R_E (--teacher-keep pareto, buffers.py): a full R_E drops one beaten on return and return per step (step 2).
"""

import os
import sys

import plumbing

if __name__ == "__main__":
    plumbing.quiet_interrupt_while_importing("sail.py")

import argparse
import dataclasses
import time

import numpy as np
import torch

import cpu_kernels
from buffers import ReplayBuffer, TeacherBuffer, mixed_batch
from credit import RewardModel, decomposition_unit, return_bonus, train_reward_model
from demos import default_demo_path, load_teacher_buffer
from discriminator import Discriminator, shaped_reward, train_discriminator
from envs import EnvState, evaluate_policy, make_env
from td3 import TD3, make_adam

# Presets of --algo: defaults that flags given still override. The baselines keep their papers' plain learner.
PLAIN_LEARNER = {"critic_layer_norm": False, "disc_negatives": "all", "return_decomposition": 0.0,
                 "decomposition_unit": "range", "decomposition_subset": 64, "disc_action_norm": False,
                 "action_cost": "none", "teacher_keep": "return"}  # K = 64: RRD's code's rrd_sample_size for MuJoCo
PRESETS = {
    "sail": {},
    "sail-paper": PLAIN_LEARNER | {"return_bonus": 0.0},  # Algorithm 1 as published
    # DAC (Kostrikov et al. 2019): absorbing states, AIRL-style reward, no mixing, no adaptation
    "dac": PLAIN_LEARNER | {"absorbing": True, "time_feature": False, "reward": "airl", "alpha": 0.0,
                            "no_adaptation": True, "return_bonus": 0.0},
    # TD3 on the sparse episodic reward alone: no demos, no discriminator
    "td3": PLAIN_LEARNER | {"reward": "env", "alpha": 0.0, "no_adaptation": True, "return_bonus": 0.0},
    # IRCR (Gangwani et al. 2020): TD3 on the return bonus alone; no demos, no discriminator
    "ircr": PLAIN_LEARNER | {"reward": "none", "alpha": 0.0, "no_adaptation": True},
    # RRD (Ren et al. 2022): TD3 on the learned per-step reward alone; no demos, no discriminator
    "rrd": PLAIN_LEARNER | {"reward": "none", "alpha": 0.0, "no_adaptation": True, "return_bonus": 0.0,
                            "return_decomposition": 1.0},
}
PRESET_NAMES = {"sail": "SAIL", "sail-paper": "SAIL-paper", "dac": "DAC", "td3": "TD3 (sparse)", "ircr": "IRCR",
                "rrd": "RRD"}
# what --resume RUN_DIR may change; every other flag is the saved run's
RESUMABLE = ("total_timesteps", "threads", "device")
# flags that say how a run is set up, measured or stored, not what it learns
SETUP = {"env", "algo", "method", "seed", "total_timesteps", "eval_freq", "eval_episodes", "demos", "num_demos",
         "device", "threads", "kernels", "output_dir", "run_name", "tensorboard", "resume"}


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    on_off, pos, nonneg = argparse.BooleanOptionalAction, plumbing.positive_int, plumbing.non_negative_float
    g = p.add_argument_group("experiment")
    g.add_argument("--env", default="Walker2d-v5", help="gymnasium env id (MuJoCo v5 or any Box-action env)")
    g.add_argument("--algo", choices=sorted(PRESETS), default="sail", help="method: SAIL or a baseline preset")
    g.add_argument("--method", help="what the run is, for config.json and plot.py (default: the preset's name)")
    g.add_argument("--seed", type=plumbing.seed, default=1, help="seed of env, action space, numpy and torch")
    g.add_argument("--total-timesteps", type=pos, default=1_000_000, help="env steps of the run")
    g.add_argument("--learning-starts", type=pos, default=10_000, help="random steps before any update")
    g.add_argument("--eval-freq", type=pos, default=10_000, help="env steps between evaluations and checkpoints")
    g.add_argument("--eval-episodes", type=pos, default=5, help="episodes per evaluation")
    g.add_argument("--demos", help="demo file or Minari dataset (default: demos/<env>.npz)")
    g.add_argument("--num-demos", type=pos, default=1, help="teacher episodes used from the demo file")
    g.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu", help="torch device")
    g.add_argument("--threads", type=plumbing.threads, default=2, help="torch CPU threads")
    g.add_argument("--kernels", choices=["auto", "torch", "onednn"], default="auto", help="CPU matmul kernels")
    g.add_argument("--output-dir", default="runs", help="parent folder of the run folder")
    g.add_argument("--run-name", help="run folder name (default: <env>__<algo>__<seed>__<time>)")
    g.add_argument("--tensorboard", action="store_true", help="also log progress.csv as TensorBoard scalars")
    g.add_argument("--resume", metavar="RUN_DIR", help="continue the run saved in RUN_DIR with its flags")
    g = p.add_argument_group("TD3 learner")
    g.add_argument("--hidden", type=pos, nargs="+", default=[256, 256], help="actor/critic hidden sizes")
    g.add_argument("--lr", type=plumbing.positive_float, default=3e-4, help="Adam learning rate of actor and critic")
    g.add_argument("--gamma", type=plumbing.unit_interval, default=0.99, help="discount")
    g.add_argument("--tau", type=plumbing.unit_interval, default=0.005, help="Polyak averaging rate of target networks")
    g.add_argument("--batch-size", type=pos, default=256, help="TD3 batch; also R_E's and R_B's part of D's")
    g.add_argument("--policy-noise", type=nonneg, default=0.2, help="target policy smoothing noise std")
    g.add_argument("--noise-clip", type=nonneg, default=0.5, help="target policy smoothing noise clip")
    g.add_argument("--policy-delay", type=pos, default=2, help="critic updates per actor update")
    g.add_argument("--exploration-noise", type=nonneg, default=0.1, help="std of the Gaussian action noise")
    g.add_argument("--buffer-size", type=pos, default=1_000_000, help="capacity of R_B in transitions")
    g.add_argument("--critic-layer-norm", action=on_off, default=True, help="LayerNorm in the critics (RLPD's)")
    g = p.add_argument_group("reward")
    g.add_argument("--reward", choices=["sail", "airl", "env", "none"], default="sail",
                   help="-log(1-D), log D - log(1-D), the sparse env reward, or none (the credit alone)")
    g.add_argument("--return-bonus", type=nonneg, default=1.0, help="weight of the episode's scaled return (IRCR)")
    g.add_argument("--return-decomposition", type=nonneg, default=1.0, help="weight of the learned reward (RRD)")
    g.add_argument("--decomposition-unit", choices=["range", "rate"], default="rate",
                   help="learned reward's unit: range of returns per step, or over the time limit (RRD's)")
    g.add_argument("--action-cost", choices=["none", "reward", "reward-and-actor"], default="reward-and-actor",
                   help="a learned c ||a||^2 in the learned reward, and also in the actor's loss")
    g.add_argument("--decomposition-subset", type=pos, default=256, help="steps per episode per minibatch (RRD's K; "
                   "at least the episode length: whole episodes, one a minibatch)")
    g.add_argument("--time-feature", action=on_off, default=True, help="append 1 - t/T to the observation")
    g.add_argument("--absorbing", action=on_off, default=False, help="DAC's absorbing states")
    g = p.add_argument_group("discriminator")
    g.add_argument("--disc-hidden", type=pos, nargs="+", default=[256, 256], help="hidden sizes (tanh)")
    g.add_argument("--disc-lr", type=plumbing.positive_float, default=1e-3, help="Adam learning rate")
    g.add_argument("--disc-freq", type=pos, default=500, help="env steps between discriminator trainings")
    g.add_argument("--disc-steps", type=pos, default=10, help="minibatches per discriminator training")
    g.add_argument("--grad-penalty", type=nonneg, default=10.0, help="gradient penalty weight")
    g.add_argument("--entropy-coef", type=nonneg, default=0.01, help="Bernoulli entropy bonus weight")
    g.add_argument("--disc-action-norm", action=on_off, default=True, help="normalise D's actions as its states")
    g = p.add_argument_group("SAIL and its ablations")
    g.add_argument("--alpha", type=float, default=0.5, help="R_E's share of TD3 batches before a promotion (0: no LfD)")
    g.add_argument("--teacher-capacity", type=pos, default=10_000, help="capacity of R_E in transitions")
    g.add_argument("--teacher-keep", choices=["return", "pareto"], default="pareto",
                   help="whom a full R_E drops first: the lowest return, or one beaten on return and return per step")
    g.add_argument("--fixed-alpha", action="store_true", help="ablation: alpha stays at --alpha")
    g.add_argument("--no-adaptation", action="store_true", help="ablation: R_E is never updated")
    g.add_argument("--disc-negatives", choices=["all", "recent", "recent-after-promotion"],
                   default="recent-after-promotion", help="D's negatives: all of R_B (the paper's), recent steps")
    g.add_argument("--on-policy-window", type=pos, default=2_000, help="how many recent steps are recent")

    argv = sys.argv[1:] if argv is None else argv
    p.set_defaults(**PRESETS[p.parse_known_args(argv)[0].algo])
    args = p.parse_args(argv)
    args.given = p.given_flags(argv)
    check_args(p, args)
    plumbing.check_tensorboard(p, args)
    args.method = args.method or method_name(args)
    return args


def check_args(p, args):
    """What a single flag's type cannot check (counts and rates are checked by their types)."""
    if not 0.0 <= args.alpha <= 1.0:
        p.error(f"--alpha must be in [0, 1], got {args.alpha}")
    if args.total_timesteps <= args.learning_starts and not args.resume:
        p.error(f"--total-timesteps {args.total_timesteps} ends before --learning-starts {args.learning_starts}")
    if args.reward in ("env", "none") and not (args.alpha == 0 and args.no_adaptation):
        p.error(f"--reward {args.reward} learns without demos: it needs --alpha 0 and --no-adaptation "
                f"(or --algo {'td3' if args.reward == 'env' else 'ircr'})")
    if args.reward == "none" and args.return_bonus <= 0 and args.return_decomposition <= 0:
        p.error("--reward none needs --return-bonus > 0 or --return-decomposition > 0")
    if args.action_cost != "none" and args.return_decomposition <= 0:  # the default turns off with what it needs
        if "action_cost" in args.given:
            p.error(f"--action-cost {args.action_cost} is part of the learned reward: it needs --return-decomposition")
        args.action_cost = "none"
    if args.buffer_size < 1001:
        p.error("--buffer-size must hold at least one whole episode (1001 transitions)")
    if args.eval_freq > args.total_timesteps and not args.resume:
        p.error(f"--eval-freq {args.eval_freq} is more than --total-timesteps {args.total_timesteps}: no progress.csv")
    if args.absorbing and (args.reward in ("env", "none") or args.return_bonus > 0 or args.return_decomposition > 0):
        p.error("--absorbing counts its self-loop's reward forever, meant for D's (DAC): it needs --reward sail "
                "or airl, --return-bonus 0 and --return-decomposition 0")


def method_name(args):
    """The preset's name, and the learner flags given on the command line: "SAIL-paper (--fixed-alpha)"."""
    flags = [plumbing.as_flag(name, getattr(args, name)) for name in sorted(args.given - SETUP)]
    return PRESET_NAMES[args.algo] + (f" ({' '.join(flags)})" if flags else "")


def update(parts, s, args, unit):
    """A minibatch of the reward model, then Eqs. (7) and (8): one TD3 step on a batch of
    alpha R_E + (1 - alpha) R_B, with the reward r'."""
    agent, disc, reward_model = parts["agent"], parts["disc"], parts.get("reward_model")
    stats = {} if reward_model is None else train_reward_model(
        reward_model, parts["reward_optimizer"], parts["self_buffer"], args.batch_size, args.decomposition_subset)
    batch, env_rewards, episode_returns = mixed_batch(parts["teacher_buffer"], parts["self_buffer"], args.batch_size,
                                                      s.alpha, with_returns=args.return_bonus > 0)
    obs, actions, next_obs, terminated = (x.to(agent.device) for x in batch)
    if args.reward == "env":  # the TD3-sparse baseline: the env's own (sparse episodic) reward
        rewards = env_rewards.to(agent.device)
    elif args.reward == "none":  # IRCR and RRD: the credit below is the whole reward
        rewards = torch.zeros(len(obs), device=agent.device)
    else:
        rewards = shaped_reward(disc, obs, actions, args.reward)
    if args.return_bonus > 0:
        rewards = rewards + args.return_bonus * return_bonus(episode_returns.to(agent.device), s.return_range)
    actor_penalty = None
    if reward_model is not None:  # in the unit of the per-step returns seen, whatever the reward's scale
        with torch.no_grad():
            learned = reward_model(obs, actions, next_obs)
        rewards = rewards + args.return_decomposition * learned / unit
        if args.action_cost == "reward-and-actor":  # the learned c ||a||^2, as the critic's reward carries it
            cost = args.return_decomposition * reward_model.action_cost().detach() / unit
            actor_penalty = lambda policy_actions: cost * policy_actions.pow(2).sum(-1)  # noqa: E731
    # DAC: in the absorbing state the only action is zero, as the agent and the demos act there
    next_action_mask = 1.0 - next_obs[:, -1:] if args.absorbing else None
    losses = agent.update(obs, actions, rewards, next_obs, terminated, next_action_mask, actor_penalty)
    return stats | losses | {"reward_mean": rewards.mean()}


@dataclasses.dataclass
class LoopState:
    """Everything the loop carries from step to step besides networks, buffers and envs."""
    alpha: float
    kernels: str                        # the CPU kernels chosen at the start (kept on --resume)
    global_step: int = 0
    episode_start: int = 0              # R_B's write position when the current episode began
    promotions: int = 0
    first_promotion_step: int | None = None
    train_episodic_return: float = float("nan")
    return_range: tuple = (float("inf"), -float("inf"))  # lowest and highest episodic returns seen (R_E's too)
    rate_range: tuple = (float("inf"), -float("inf"))    # the same for return / length
    train_time: float = 0.0             # seconds of training (evaluations excluded)
    rows: list = dataclasses.field(default_factory=list)  # progress.csv

    def record_return(self, ret, length):
        """An episode's return into the ranges that scale the return bonus and the learned reward."""
        self.return_range = (min(self.return_range[0], ret), max(self.return_range[1], ret))
        self.rate_range = (min(self.rate_range[0], ret / length), max(self.rate_range[1], ret / length))


def build(args, device, use_demos):
    """What a run's checkpoint holds, each part with state_dict / load_state_dict, seeded: both envs,
    R_E (the demos; on --resume, the checkpoint's), R_B, the TD3 agent, D, the reward model and the RNGs."""
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    env = make_env(args.env, args.seed, time_feature=args.time_feature, absorbing=args.absorbing)
    eval_env = make_env(args.env, args.seed + 100, time_feature=args.time_feature, absorbing=args.absorbing)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    teacher_buffer = (load_teacher_buffer(args.demos or default_demo_path(args.env), args.env, env, args.num_demos,
                                          args.teacher_capacity, args.time_feature, args.absorbing, args.teacher_keep)
                      if use_demos and not args.resume else TeacherBuffer(args.teacher_capacity, args.teacher_keep))
    agent = TD3(obs_dim, act_dim, env.action_space.low, env.action_space.high, args.hidden, args.lr,
                gamma=args.gamma, tau=args.tau, policy_noise=args.policy_noise, noise_clip=args.noise_clip,
                policy_delay=args.policy_delay, device=device, critic_layer_norm=args.critic_layer_norm)
    self_buffer = ReplayBuffer(obs_dim, act_dim, args.buffer_size)
    disc = Discriminator(obs_dim, act_dim, args.disc_hidden, args.disc_action_norm).to(device)
    parts = {"agent": agent, "disc": disc, "disc_optimizer": make_adam(disc.parameters(), args.disc_lr),
             "self_buffer": self_buffer, "teacher_buffer": teacher_buffer, "env": EnvState(env),
             "eval_env": EnvState(eval_env), "rng": plumbing.RNGs(np.random.default_rng(args.seed))}
    if args.return_decomposition > 0:
        reward_model = RewardModel(obs_dim, act_dim, args.hidden, args.action_cost != "none").to(device)
        reward_optimizer = make_adam(reward_model.parameter_groups(args.lr), args.lr)
        parts |= {"reward_model": reward_model, "reward_optimizer": reward_optimizer}
    return parts


def start(args, parts, device):
    """The run folder, the loop's state, the first observation and the latest losses: those of the run in
    --resume's folder, its parts loaded from its checkpoint; else a new run folder."""
    agent, disc, reward_model = parts["agent"], parts["disc"], parts.get("reward_model")
    if args.resume:
        saved = plumbing.load_checkpoint(os.path.join(args.resume, "checkpoint.pt"), parts)
        s, obs, stats = LoopState(**saved["loop"]), saved["obs"], dict(saved["stats"])
        plumbing.record_resume(args.resume, args, s.global_step, RESUMABLE)
        run_dir = args.resume
    else:
        kernels = cpu_kernels.choose(args.kernels, [agent.actor.net, agent.critic.q1.net, disc.net],
                                     args.batch_size, device)
        s, stats = LoopState(alpha=args.alpha, kernels=kernels), {}
        for ret, data in parts["teacher_buffer"].episodes:
            s.record_return(ret, len(data[0]))
        obs, _ = parts["env"].env.reset()
        config = vars(args) | {"script": "sail.py", "kernels_chosen": kernels}  # make_run_dir drops "given"
        run_dir = plumbing.make_run_dir(args.output_dir, args.run_name or plumbing.run_name(
            args.env, args.algo, args.seed), config)
    cpu_kernels.apply(s.kernels, [*agent.networks(), disc, *([reward_model] if reward_model else [])])
    return run_dir, s, obs, stats


def train(args):
    if args.resume:
        args = plumbing.resume_config(args.resume, args, args.given, RESUMABLE, "sail.py")
    device = plumbing.torch_device(args.device)
    use_demos = args.reward in ("sail", "airl")  # D's reward needs R_E; the env's, IRCR's and RRD's do not
    parts = build(args, device, use_demos)
    agent, disc, teacher_buffer, self_buffer = (parts[k] for k in ("agent", "disc", "teacher_buffer", "self_buffer"))
    env, eval_env, rng = parts["env"].env, parts["eval_env"].env, parts["rng"].rng

    # From here on Ctrl-C and SIGTERM only set stop.requested: the loop stops, checkpoints, and can resume
    with plumbing.StopRequest() as stop:
        run_dir, s, obs, stats = start(args, parts, device)  # stats: the latest losses, logged at each evaluation

        def learning(step):
            """After the warm-up; with the return bonus or decomposition, also once an episode of its
            own has ended and two different returns were seen, since both scale by their range."""
            return step >= args.learning_starts and not ((args.return_bonus > 0 or args.return_decomposition > 0) and (
                np.isnan(s.train_episodic_return) or s.return_range[0] >= s.return_range[1]))
        was_learning = learning(s.global_step)

        def count_time():  # training seconds since the last call (evaluations are not counted)
            nonlocal clock
            s.train_time, clock = s.train_time + (now := time.perf_counter()) - clock, now

        def save_checkpoint():
            plumbing.save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts, loop=dataclasses.asdict(s),
                                     obs=obs, stats={k: float(v) for k, v in stats.items()})

        print(f"run folder: {run_dir}\nCPU: {plumbing.cpu_model()}, kernels: {s.kernels}", flush=True)
        if use_demos:
            print(f"teacher: {plumbing.count(teacher_buffer.num_episodes, 'episode')}, "
                  f"return {np.mean(teacher_buffer.returns):.1f}", flush=True)
        log = plumbing.ProgressLog(run_dir, plumbing.PROGRESS_COLUMNS, s.rows, args.tensorboard)
        bar = plumbing.progress_bar(args.total_timesteps, s.global_step, f"{args.algo} {args.env}",
                                    args.learning_starts, s.rows[-1] if s.rows else None)
        clock, last_row = time.perf_counter(), (s.global_step, s.train_time)
        with bar:  # closed however the loop ends, an error too
            while s.global_step < args.total_timesteps and not stop.requested:
                s.global_step += 1

                # 1. act: uniformly random while R_B is initialised, then the actor plus Gaussian noise
                action = (agent.explore(obs, args.exploration_noise, rng) if learning(s.global_step - 1)
                          else env.action_space.sample())
                if args.absorbing and obs[-1] == 1.0:  # the absorbing state: a zero action, as in the demos
                    action = np.zeros_like(action)
                next_obs, reward, terminated, truncated, info = env.step(action)
                self_buffer.add(obs, action, reward, next_obs, terminated)
                obs = next_obs

                # 2. adaptive teacher buffer: an episode better than the worst in R_E joins it whole; alpha -> 0
                if terminated or truncated:
                    s.train_episodic_return = float(info["episode"]["r"])
                    length = (self_buffer.ptr - s.episode_start) % args.buffer_size
                    self_buffer.end_episode(s.episode_start, s.train_episodic_return)
                    s.record_return(s.train_episodic_return, length or args.buffer_size)
                    if not args.no_adaptation and teacher_buffer.promote(s.train_episodic_return,
                                                                         *self_buffer.latest(length)):
                        s.promotions += 1
                        s.first_promotion_step = s.first_promotion_step or s.global_step
                        s.alpha = s.alpha if args.fixed_alpha else 0.0
                    obs, _ = env.reset()
                    s.episode_start = self_buffer.ptr

                if learning(s.global_step):
                    # 3. discriminator, Eq. (4): R_E against all of R_B (off-policy) or against its recent steps
                    if use_demos and (not was_learning or (s.global_step - args.learning_starts) % args.disc_freq == 0):
                        recent = args.disc_negatives == "recent" or (args.disc_negatives == "recent-after-promotion"
                                                                     and s.first_promotion_step is not None)
                        stats.update(train_discriminator(disc, parts["disc_optimizer"], teacher_buffer, self_buffer,
                                                         args.disc_steps, args.batch_size, args.entropy_coef,
                                                         args.grad_penalty, args.on_policy_window if recent else None))
                    was_learning = True

                    # 4. TD3 on the mixture alpha R_E + (1 - alpha) R_B, rewarded by r'(s, a): Eqs. (7), (8)
                    unit = decomposition_unit(args.decomposition_unit, s.return_range, s.rate_range,
                                              env.max_episode_steps)
                    stats.update(update(parts, s, args, unit))
                    # stop before a diverged actor acts in the env; the last checkpoint stays good
                    plumbing.check_finite(stats, f"at step {s.global_step}", run_dir)

                # 5. evaluation of the deterministic policy, the CSV row and a checkpoint
                if s.global_step % args.eval_freq == 0:
                    count_time()
                    row = {"global_step": s.global_step, **evaluate_policy(eval_env, agent.act, args.eval_episodes),
                           "train_episodic_return": s.train_episodic_return,
                           "teacher_threshold": teacher_buffer.threshold if use_demos else float("nan"),
                           "teacher_episodes": teacher_buffer.num_episodes, "promotions": s.promotions,
                           "alpha": s.alpha, "updates": agent.num_updates, "time": s.train_time,
                           "steps_per_second": (s.global_step - last_row[0]) / max(s.train_time - last_row[1], 1e-9)}
                    log.append(row | {k: float(stats.get(k, float("nan"))) for k in plumbing.PROGRESS_COLUMNS
                                      if k not in row})
                    save_checkpoint()
                    plumbing.show_row(bar, row)
                    clock, last_row = time.perf_counter(), (s.global_step, s.train_time)  # evaluation left out
                bar.update(1)
        count_time()
        save_checkpoint()
    plumbing.save_model(run_dir, agent, disc, args)
    if stop.requested:
        print(f"stopped at step {s.global_step}: checkpoint saved, continue with --resume {run_dir}")
    return stop.exit_code


def main(argv=None):
    return plumbing.run_main("sail.py", train, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
