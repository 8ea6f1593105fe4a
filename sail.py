"""SAIL: Self-Adaptive Imitation Learning (Zhu, Lin, Dai, Zhou), in one file.

    python sail.py --env Walker2d-v5

The environment only returns, when an episode ends, the episodic return r_e (envs.py). The agent
starts from one to four episodes of a sub-optimal teacher (demos/<env>.npz) and
  1. trains a discriminator D(s, a) off-policy to tell the teacher buffer R_E (label 1) from its
     own replay buffer R_B (label 0), Eq. (discriminator);
  2. learns with TD3 from the reward r'(s, a) = -log(1 - D(s, a)), on batches mixed from both
     buffers with ratio alpha (Eq. qgrad / pigrad);
  3. whenever one of its episodes scores more than the worst teacher episode, adds it to R_E
     whole, and sets alpha to 0 (Algorithm 1): the target it imitates keeps getting better.
The paper's ablations are flags (--fixed-alpha, --no-lfd, --no-adaptation, --on-policy-disc),
its baselines are presets of the same loop (--algo dac, bc, td3). README.md lists every flag.
"""

import argparse
import csv
import io
import json
import math
import os
import shlex
import signal
import sys
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

from buffers import ReplayBuffer, TeacherBuffer, atomic_write, default_demo_path, load_demos, mixed_batch
from envs import ArgumentParser, ConfigError, add_features, first_line, get_env_state, make_env, rollout, set_env_state
from td3 import MLP, TD3, make_adam

# Presets of --algo: each sets defaults that explicit flags still override.
PRESETS = {
    "sail": {},
    # DAC (Kostrikov et al. 2019): absorbing states, AIRL-style reward, no mixing, no adaptation
    "dac": {"absorbing": True, "time_feature": False, "reward": "airl", "no_lfd": True, "no_adaptation": True},
    # TD3 on the sparse episodic reward alone: no demos, no discriminator
    "td3": {"reward": "env", "no_lfd": True, "no_adaptation": True},
    # behaviour cloning: supervised regression of the teacher's actions, no env interaction
    "bc": {},
}


def parse_args(argv=None):
    p = ArgumentParser(description=__doc__.split("\n\n")[0])
    g = p.add_argument_group("experiment")
    g.add_argument("--env", default="Walker2d-v5", help="gymnasium env id (MuJoCo v5 or any Box-action env)")
    g.add_argument("--algo", choices=sorted(PRESETS), default="sail", help="method: SAIL or a baseline preset")
    g.add_argument("--seed", type=int, default=1, help="seed of env, action space, numpy and torch")
    g.add_argument("--total-timesteps", type=int, default=1_000_000, help="env steps of the run")
    g.add_argument("--learning-starts", type=int, default=10_000,
                   help="uniformly random steps that initialise R_B before any update")
    g.add_argument("--eval-freq", type=int, default=10_000,
                   help="env steps between evaluations of the deterministic policy (BC: gradient steps)")
    g.add_argument("--eval-episodes", type=int, default=5, help="episodes per evaluation")
    g.add_argument("--demos", help="demo file (default: demos/<env>.npz)")
    g.add_argument("--num-demos", type=int, default=1, help="teacher episodes used from the demo file")
    g.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu", help="torch device")
    g.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    g.add_argument("--output-dir", default="runs", help="parent folder of the run folder")
    g.add_argument("--run-name", help="run folder name (default: <env>__<algo>__<seed>__<time>)")
    g.add_argument("--save-model", action="store_true", help="save the networks to model.pt at the end")
    g.add_argument("--resume", metavar="RUN_DIR", help="continue the run saved in RUN_DIR "
                   "(its flags are reused; --total-timesteps, --threads and --device may be changed)")
    g.add_argument("--checkpoint-freq", type=int, default=50_000, help="env steps between checkpoints")
    g.add_argument("--evaluate", metavar="RUN_DIR", help="only run --eval-episodes episodes of RUN_DIR's saved actor "
                   "(model.pt, else checkpoint.pt) on an env seeded with --seed, print return and length of each")

    g = p.add_argument_group("TD3 learner")
    g.add_argument("--hidden", type=int, nargs="+", default=[256, 256], help="actor/critic hidden sizes")
    g.add_argument("--lr", type=float, default=3e-4, help="Adam learning rate of actor and critic")
    g.add_argument("--gamma", type=float, default=0.99, help="discount")
    g.add_argument("--tau", type=float, default=0.005, help="Polyak averaging rate of target networks")
    g.add_argument("--batch-size", type=int, default=256, help="critic/actor batch size")
    g.add_argument("--policy-noise", type=float, default=0.2, help="target policy smoothing noise std")
    g.add_argument("--noise-clip", type=float, default=0.5, help="target policy smoothing noise clip")
    g.add_argument("--policy-delay", type=int, default=2, help="critic updates per actor update")
    g.add_argument("--exploration-noise", type=float, default=0.1, help="std of Gaussian action noise")
    g.add_argument("--buffer-size", type=int, default=1_000_000, help="capacity of R_B in transitions")
    g.add_argument("--update-every", type=int, default=1,
                   help="env steps between groups of as many TD3 updates (authors: 1000)")
    g.add_argument("--reward", choices=["sail", "airl", "env"], default="sail",
                   help="critic reward: sail = -log(1-D), airl = log D - log(1-D), env = sparse env reward")
    g.add_argument("--time-feature", action=argparse.BooleanOptionalAction, default=True, help="append 1 - t/T to obs")
    g.add_argument("--absorbing", action=argparse.BooleanOptionalAction, default=False, help="DAC absorbing states")

    g = p.add_argument_group("discriminator")
    g.add_argument("--disc-hidden", type=int, nargs="+", default=[256, 256], help="hidden sizes (tanh)")
    g.add_argument("--disc-lr", type=float, default=1e-3, help="Adam learning rate")
    g.add_argument("--disc-freq", type=int, default=500, help="env steps between discriminator trainings")
    g.add_argument("--disc-steps", type=int, default=10, help="minibatches per discriminator training")
    g.add_argument("--disc-batch-size", type=int, default=256, help="teacher and self samples per minibatch")
    g.add_argument("--grad-penalty", type=float, default=10.0, help="gradient penalty weight")
    g.add_argument("--entropy-coef", type=float, default=0.01, help="Bernoulli entropy bonus weight")

    g = p.add_argument_group("SAIL and its ablations")
    g.add_argument("--alpha", type=float, default=0.5, help="initial share of teacher samples in batches")
    g.add_argument("--alpha-anneal-steps", type=int, default=0,
                   help="after the first promotion, anneal alpha linearly to 0 over this many steps "
                        "(0: switch at once, as the authors' code)")
    g.add_argument("--teacher-capacity", type=int, default=10_000, help="capacity of R_E in transitions")
    g.add_argument("--fixed-alpha", action="store_true", help="ablation: alpha stays at --alpha")
    g.add_argument("--no-lfd", action="store_true", help="ablation: alpha = 0 always (no teacher samples)")
    g.add_argument("--no-adaptation", action="store_true", help="ablation: R_E is never updated")
    g.add_argument("--on-policy-disc", action="store_true",
                   help="ablation: D's negatives are the most recent samples, not the whole R_B")
    g.add_argument("--on-policy-window", type=int, default=2_000,
                   help="recent transitions that --on-policy-disc draws negatives from")
    g.add_argument("--bc-steps", type=int, default=20_000, help="BC: gradient steps")

    argv = sys.argv[1:] if argv is None else argv
    known, _ = p.parse_known_args(argv)
    p.set_defaults(**PRESETS[known.algo])
    args = p.parse_args(argv)
    args.given = {k for k, v in vars(args).items() if v != p.get_default(k)}
    check_args(p, args)
    return args


def check_args(p, args):
    positive = ["total_timesteps", "eval_freq", "eval_episodes", "num_demos", "threads", "batch_size",
                "policy_delay", "buffer_size", "update_every", "disc_freq", "disc_steps", "disc_batch_size",
                "teacher_capacity", "on_policy_window", "bc_steps", "checkpoint_freq"]
    for name in positive:
        if getattr(args, name) <= 0:
            p.error(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.learning_starts < 1:
        p.error("--learning-starts must be >= 1")
    for name in ["alpha_anneal_steps", "exploration_noise", "policy_noise", "noise_clip",
                 "grad_penalty", "entropy_coef", "lr", "disc_lr", "tau"]:
        if getattr(args, name) < 0:
            p.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    if not 0.0 <= args.alpha <= 1.0:
        p.error(f"--alpha must be in [0, 1], got {args.alpha}")
    if not 0.0 < args.gamma <= 1.0:
        p.error(f"--gamma must be in (0, 1], got {args.gamma}")
    if args.reward == "env" and args.algo != "bc" and not (args.no_lfd and args.no_adaptation):
        p.error("--reward env learns without demos: it needs --no-lfd and --no-adaptation (or --algo td3)")
    if args.buffer_size < 1001:
        p.error("--buffer-size must hold at least one whole episode (1001 transitions)")
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device is available")


# ---------------------------------------------------------------------------------------------
# The discriminator (paper, "Off-Policy Adversarial TD Learning")
# ---------------------------------------------------------------------------------------------

class Discriminator(nn.Module):
    """D(s, a) = sigmoid(logit(s, a)): teacher buffer -> 1, self buffer -> 0.

    Observations are normalised by running statistics of the data D is trained on (variance
    floor 1e-2, clipped to +-5), as in the authors' code.
    """

    def __init__(self, obs_dim, act_dim, hidden):
        super().__init__()
        self.net = MLP([obs_dim + act_dim, *hidden, 1], "tanh")
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_var", torch.ones(obs_dim))
        self.register_buffer("obs_count", torch.tensor(1e-4))

    def update_obs_stats(self, obs):
        """Parallel mean/variance update (Chan et al.) with a batch of observations."""
        n, mean, var = len(obs), obs.mean(0), obs.var(0, unbiased=False)
        total = self.obs_count + n
        delta = mean - self.obs_mean
        self.obs_mean += delta * n / total
        self.obs_var.copy_((self.obs_var * self.obs_count + var * n + delta**2 * self.obs_count * n / total) / total)
        self.obs_count.copy_(total)

    def inputs(self, obs, actions):
        obs = ((obs - self.obs_mean) / self.obs_var.clamp_min(1e-2).sqrt()).clamp(-5.0, 5.0)
        return torch.cat([obs, actions], dim=-1)

    def forward(self, x):
        """Logit of D for normalised inputs x = inputs(obs, actions)."""
        return self.net(x).squeeze(-1)


def discriminator_loss(disc, teacher_obs, teacher_act, self_obs, self_act, entropy_coef, grad_penalty):
    """Eq. (discriminator) as a BCE to minimise, minus an entropy bonus, plus a gradient penalty."""
    x_teacher, x_self = disc.inputs(teacher_obs, teacher_act), disc.inputs(self_obs, self_act)
    logits = disc(torch.cat([x_teacher, x_self]))
    labels = torch.cat([torch.ones(len(x_teacher)), torch.zeros(len(x_self))]).to(logits.device)
    bce = F.binary_cross_entropy_with_logits(logits, labels)
    # Bernoulli entropy of D's output, from the logit: softplus(-x) + (1 - sigmoid(x)) x
    entropy = (F.softplus(-logits) + (1 - torch.sigmoid(logits)) * logits).mean()
    # gradient penalty (||grad D(x_hat)|| - 1)^2 on interpolations of teacher and self inputs
    eps = torch.rand(len(x_teacher), 1, device=logits.device)
    x_hat = (eps * x_teacher + (1 - eps) * x_self).requires_grad_(True)
    grad, = torch.autograd.grad(disc(x_hat).sum(), x_hat, create_graph=True)
    penalty = (grad.norm(dim=1) - 1).pow(2).mean()
    loss = bce - entropy_coef * entropy + grad_penalty * penalty
    n = len(x_teacher)
    return loss, torch.sigmoid(logits[:n]).mean(), torch.sigmoid(logits[n:]).mean()


def shaped_reward(disc, obs, actions, kind):
    """r'(s, a) for a critic batch, from the current D."""
    with torch.no_grad():
        logit = disc(disc.inputs(obs, actions))
    if kind == "sail":
        return F.softplus(logit)  # -log(1 - D) = -log(1 - sigmoid(x)) = softplus(x), no overflow
    return logit  # airl: log D - log(1 - D) = x


def train_discriminator(disc, disc_optimizer, teacher_buffer, self_buffer, args):
    """--disc-steps minibatches of Eq. (discriminator): R_E labelled 1, R_B (or its recent part) 0."""
    device = disc.obs_mean.device
    for _ in range(args.disc_steps):
        t_obs, t_act, _, _ = teacher_buffer.sample(args.disc_batch_size)
        if args.on_policy_disc:
            b_obs, b_act, *_ = self_buffer.sample_recent(args.disc_batch_size, args.on_policy_window)
        else:
            b_obs, b_act, *_ = self_buffer.sample(args.disc_batch_size)
        t_obs, t_act, b_obs, b_act = (x.to(device) for x in (t_obs, t_act, b_obs, b_act))
        disc.update_obs_stats(torch.cat([t_obs, b_obs]))
        loss, d_teacher, d_self = discriminator_loss(disc, t_obs, t_act, b_obs, b_act,
                                                     args.entropy_coef, args.grad_penalty)
        disc_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        disc_optimizer.step()
    return {"disc_loss": loss.detach(), "disc_teacher": d_teacher.detach(), "disc_self": d_self.detach()}


def td3_update(agent, disc, teacher_buffer, self_buffer, alpha, args):
    """One TD3 step on a batch from alpha * R_E + (1 - alpha) * R_B, with the reward r'(s, a) of D."""
    batch, env_rewards = mixed_batch(teacher_buffer, self_buffer, args.batch_size, alpha)
    obs, actions, next_obs, terminated = (x.to(agent.device) for x in batch)
    if args.reward == "env":  # the TD3-sparse baseline: the env's own (sparse episodic) reward
        rewards = env_rewards.to(agent.device)
    else:
        rewards = shaped_reward(disc, obs, actions, args.reward)
    # DAC: the absorbing state's only action is zero (as the agent and the demos act there, and as
    # in DAC's code). With the actor's action instead, the critic is asked for Q at actions it never
    # saw in that state, the actor pushes them up, and the self-loop multiplies that by 1/(1 - gamma).
    next_action_mask = 1.0 - next_obs[:, -1:] if args.absorbing else None
    return agent.update(obs, actions, rewards, next_obs, terminated, next_action_mask) | {"reward_mean": rewards.mean()}


# ---------------------------------------------------------------------------------------------
# Run folder, CSV, checkpoints: everything written atomically
# ---------------------------------------------------------------------------------------------

CSV_COLUMNS = ["global_step", "eval_return", "eval_return_std", "train_episodic_return", "teacher_threshold",
               "teacher_episodes", "promotions", "alpha", "disc_loss", "disc_teacher", "disc_self",
               "reward_mean", "critic_loss", "actor_loss", "q", "updates", "steps_per_second", "time"]


def write_csv(path, rows):
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=CSV_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(path, lambda f: f.write(text.getvalue().encode()))


def make_run_dir(args):
    name = args.run_name or f"{args.env}__{args.algo}__{args.seed}__{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir = os.path.join(args.output_dir, name)
    try:
        os.makedirs(run_dir, exist_ok=False)
        probe = os.path.join(run_dir, ".write-test")
        open(probe, "w").close()
        os.remove(probe)
    except FileExistsError:
        raise ConfigError(f"run folder {run_dir} already exists (use --resume {run_dir} to continue it)") from None
    except OSError as e:
        raise ConfigError(f"cannot write the run folder {run_dir}: {e.strerror}") from None
    config = {k: v for k, v in vars(args).items() if k != "given"}
    config["command"] = shlex.join([sys.executable, *sys.argv])
    atomic_write(os.path.join(run_dir, "config.json"), lambda f: f.write(json.dumps(config, indent=2).encode()))
    return run_dir


def resume_args(args):
    """The saved run's flags; --total-timesteps, --threads and --device may be given anew."""
    path = os.path.join(args.resume, "config.json")
    if not os.path.isfile(os.path.join(args.resume, "checkpoint.pt")) or not os.path.isfile(path):
        raise ConfigError(f"--resume {args.resume}: no checkpoint.pt and config.json there")
    with open(path) as f:
        saved = json.load(f)
    for name in ("total_timesteps", "threads", "device"):
        if name in args.given:
            saved[name] = getattr(args, name)
    resumed = type(args)(**saved)
    resumed.resume, resumed.given = args.resume, args.given
    return resumed


# ---------------------------------------------------------------------------------------------
# Main: setup, then the loop of Algorithm 1
# ---------------------------------------------------------------------------------------------

def main(argv=None):
    args = parse_args(argv)
    try:
        code = evaluate_saved(args) if args.evaluate else train(args)
        sys.stdout.flush()  # here, so that a reader gone early (`| head`) is caught below, not at exit
        return code
    except ConfigError as e:
        sys.exit(f"sail.py: error: {e}")
    except KeyboardInterrupt:  # during setup or BC; the training loop handles Ctrl-C itself
        print("sail.py: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stop quietly, as Unix tools do; stdout to /dev/null so exit cannot fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def train(args):
    if args.resume:
        args = resume_args(args)
    device = torch.device("cuda" if args.device == "cuda" or (args.device == "auto" and torch.cuda.is_available())
                          else "cpu")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    env_options = {"time_feature": args.time_feature, "absorbing": args.absorbing}
    env = make_env(args.env, args.seed, **env_options)
    eval_env = make_env(args.env, args.seed + 100, **env_options)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    raw_obs_dim = obs_dim - int(args.time_feature) - int(args.absorbing)  # the demo files' observations
    low, high = env.action_space.low, env.action_space.high

    # R_E: the teacher's episodes, with the same features the env wrappers add online
    use_demos = args.algo == "bc" or args.reward != "env"
    teacher_buffer = TeacherBuffer(args.teacher_capacity)
    if use_demos:
        demo_path = args.demos or default_demo_path(args.env)
        for episode in load_demos(demo_path, args.env, raw_obs_dim, act_dim, args.num_demos):
            if len(episode["actions"]) > args.teacher_capacity:
                raise ConfigError(f"--teacher-capacity {args.teacher_capacity} is smaller than a demo episode")
            teacher_buffer.add_episode(episode["episodic_return"], *add_features(
                episode, env.max_episode_steps, args.time_feature, args.absorbing))
    teacher_return = float(np.mean(teacher_buffer.returns)) if use_demos else float("nan")

    run_dir = args.resume or make_run_dir(args)
    agent = TD3(obs_dim, act_dim, low, high, hidden=args.hidden, lr=args.lr, gamma=args.gamma, tau=args.tau,
                policy_noise=args.policy_noise, noise_clip=args.noise_clip, policy_delay=args.policy_delay,
                device=device)
    if args.algo == "bc":
        return train_bc(args, agent, teacher_buffer, eval_env, run_dir, device)
    self_buffer = ReplayBuffer(obs_dim, act_dim, args.buffer_size)
    disc = Discriminator(obs_dim, act_dim, args.disc_hidden).to(device)
    disc_optimizer = make_adam(disc.parameters(), args.disc_lr)

    # the state of the loop; a checkpoint holds all of it
    s = {"global_step": 0, "alpha": 0.0 if args.no_lfd else args.alpha, "first_promotion_step": None,
         "promotions": 0, "train_episodic_return": float("nan"), "updates": 0, "episode_start": 0,
         "rows": [], "train_time": 0.0}
    obs, _ = env.reset()
    if args.resume:
        obs = load_checkpoint(run_dir, s, agent, disc, disc_optimizer, self_buffer, teacher_buffer, env, eval_env,
                              rng)
    print(f"run folder: {run_dir}\nteacher: {teacher_buffer.num_episodes} episodes, return {teacher_return:.1f}"
          if use_demos else f"run folder: {run_dir}", flush=True)

    stats = {}  # the latest losses, logged at each evaluation
    interrupted = False

    def on_sigint(signum, frame):
        nonlocal interrupted
        interrupted = True
    previous_handler = signal.signal(signal.SIGINT, on_sigint)

    bar = tqdm(total=args.total_timesteps, initial=s["global_step"], desc=f"{args.algo} {args.env}",
               unit="step", dynamic_ncols=True, mininterval=1.0)
    tick, tick_step = time.perf_counter(), s["global_step"]
    while s["global_step"] < args.total_timesteps and not interrupted:
        s["global_step"] += 1
        global_step = s["global_step"]

        # 1. act: uniformly random while R_B is initialised, then the actor plus Gaussian noise
        if global_step <= args.learning_starts:
            action = env.action_space.sample()
        else:
            action = agent.explore(obs, args.exploration_noise, rng)
        if args.absorbing and obs[-1] == 1.0:  # the absorbing state: a zero action, as in the demos
            action = np.zeros(act_dim, np.float32)
        next_obs, reward, terminated, truncated, info = env.step(action)
        self_buffer.add(obs, action, reward, next_obs, terminated)
        obs = next_obs

        # 2. adaptive teacher buffer: a whole episode better than the worst teacher one joins R_E
        if terminated or truncated:
            s["train_episodic_return"] = info["episodic_return"]
            if not args.no_adaptation:
                length = (self_buffer.ptr - s["episode_start"]) % args.buffer_size
                idx = torch.arange(s["episode_start"], s["episode_start"] + length) % args.buffer_size
                obs_e, act_e, _, next_obs_e, term_e = self_buffer.gather(idx)
                if teacher_buffer.promote(info["episodic_return"], obs_e, act_e, next_obs_e, term_e):
                    s["promotions"] += 1
                    if s["first_promotion_step"] is None:
                        s["first_promotion_step"] = global_step
            obs, _ = env.reset()
            s["episode_start"] = self_buffer.ptr

        # dynamic alpha: args.alpha until the first promotion, then 0 (at once or annealed)
        if not (args.fixed_alpha or args.no_lfd) and s["first_promotion_step"] is not None:
            done = (global_step - s["first_promotion_step"]) / max(args.alpha_anneal_steps, 1)
            s["alpha"] = args.alpha * max(0.0, 1.0 - done) if args.alpha_anneal_steps else 0.0

        if global_step >= args.learning_starts:
            # 3. discriminator: teacher samples vs the whole R_B (off-policy), or recent ones
            if args.reward != "env" and (global_step - args.learning_starts) % args.disc_freq == 0:
                stats.update(train_discriminator(disc, disc_optimizer, teacher_buffer, self_buffer, args))

            # 4. TD3 on the mixture alpha * R_E + (1 - alpha) * R_B, rewarded by r'(s, a)
            if global_step % args.update_every == 0:
                for _ in range(args.update_every):
                    stats.update(td3_update(agent, disc, teacher_buffer, self_buffer, s["alpha"], args))
                s["updates"] = agent.num_updates
                check_finite(stats, run_dir, bar)  # stop before a diverged actor acts in the env

        # 5. evaluation of the deterministic policy; the CSV row; a checkpoint
        if global_step % args.eval_freq == 0:
            now = time.perf_counter()
            sps = (global_step - tick_step) / (now - tick)
            s["train_time"] += now - tick
            returns = [rollout(eval_env, agent.act)["episodic_return"] for _ in range(args.eval_episodes)]
            row = {"global_step": global_step, "eval_return": np.mean(returns), "eval_return_std": np.std(returns),
                   "train_episodic_return": s["train_episodic_return"],
                   "teacher_threshold": teacher_buffer.threshold if use_demos else float("nan"),
                   "teacher_episodes": teacher_buffer.num_episodes, "promotions": s["promotions"],
                   "alpha": s["alpha"], "updates": s["updates"], "steps_per_second": sps,
                   "time": s["train_time"]}
            row.update({k: float(stats[k]) if k in stats else float("nan") for k in
                        ("disc_loss", "disc_teacher", "disc_self", "reward_mean", "critic_loss", "actor_loss", "q")})
            s["rows"].append({k: round_float(v) for k, v in row.items()})
            write_csv(os.path.join(run_dir, "progress.csv"), s["rows"])
            bar.set_postfix(eval=f"{row['eval_return']:.0f}", threshold=f"{row['teacher_threshold']:.0f}",
                            alpha=s["alpha"], refresh=False)
            tick, tick_step = time.perf_counter(), global_step
        if global_step % args.checkpoint_freq == 0:
            save_checkpoint(run_dir, s, agent, disc, disc_optimizer, self_buffer, teacher_buffer, env, eval_env,
                            rng, obs)
        bar.update(1)
    bar.close()
    signal.signal(signal.SIGINT, previous_handler)

    save_checkpoint(run_dir, s, agent, disc, disc_optimizer, self_buffer, teacher_buffer, env, eval_env, rng, obs)
    if args.save_model:
        save_model(run_dir, agent, disc, args)
    if interrupted:
        print(f"interrupted at step {s['global_step']}: checkpoint saved, continue with --resume {run_dir}")
        return 130
    return 0


# ---------------------------------------------------------------------------------------------
# Behaviour cloning baseline
# ---------------------------------------------------------------------------------------------

def train_bc(args, agent, teacher_buffer, eval_env, run_dir, device):
    """Regresses the teacher's actions (MSE) with the TD3 actor; no env interaction."""
    optimizer = make_adam(agent.actor.parameters(), args.lr)
    rows = []
    for step in tqdm(range(1, args.bc_steps + 1), desc=f"bc {args.env}", unit="update", mininterval=1.0):
        obs, actions, _, _ = (x.to(device) for x in teacher_buffer.sample(args.batch_size))
        loss = F.mse_loss(agent.actor(obs), actions)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % args.eval_freq == 0 or step == args.bc_steps:
            if not math.isfinite(loss.item()):
                raise ConfigError(f"BC loss is {loss.item()} at step {step}")
            returns = [rollout(eval_env, agent.act)["episodic_return"] for _ in range(args.eval_episodes)]
            rows.append({k: float("nan") for k in CSV_COLUMNS} | {
                "global_step": 0, "updates": step, "eval_return": round_float(np.mean(returns)),
                "eval_return_std": round_float(np.std(returns)), "teacher_threshold": teacher_buffer.threshold,
                "teacher_episodes": teacher_buffer.num_episodes, "alpha": 1.0, "actor_loss": round_float(loss.item())})
            write_csv(os.path.join(run_dir, "progress.csv"), rows)
    if args.save_model:
        save_model(run_dir, agent, None, args)
    return 0


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------

def round_float(v):
    return round(float(v), 4) if isinstance(v, (float, np.floating)) else v


def check_finite(stats, run_dir, bar):
    bad = {k: float(v) for k, v in stats.items() if not math.isfinite(float(v))}
    if bad:
        bar.close()
        sys.exit(f"sail.py: error: non-finite loss {bad}; stopped, the last good checkpoint in {run_dir} is kept")


def save_checkpoint(run_dir, s, agent, disc, disc_optimizer, self_buffer, teacher_buffer, env, eval_env, rng, obs):
    state = {"loop": s, "agent": agent.state_dict(), "disc": disc.state_dict(),
             "disc_optimizer": disc_optimizer.state_dict(), "self_buffer": self_buffer.state_dict(),
             "teacher_buffer": teacher_buffer.state_dict(), "env": get_env_state(env),
             "eval_env": get_env_state(eval_env), "obs": obs, "numpy_rng": rng.bit_generator.state,
             "torch_rng": torch.get_rng_state(),
             "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}
    atomic_write(os.path.join(run_dir, "checkpoint.pt"), lambda f: torch.save(state, f))


def load_checkpoint(run_dir, s, agent, disc, disc_optimizer, self_buffer, teacher_buffer, env, eval_env, rng):
    try:
        state = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    except Exception as e:  # a checkpoint is written atomically; this is another program's file
        raise ConfigError(f"cannot read {run_dir}/checkpoint.pt: {first_line(e)}") from None
    s.update(state["loop"])
    agent.load_state_dict(state["agent"])
    disc.load_state_dict(state["disc"])
    disc_optimizer.load_state_dict(state["disc_optimizer"])
    self_buffer.load_state_dict(state["self_buffer"])
    teacher_buffer.load_state_dict(state["teacher_buffer"])
    set_env_state(env, state["env"])
    set_env_state(eval_env, state["eval_env"])
    rng.bit_generator.state = state["numpy_rng"]
    torch.set_rng_state(state["torch_rng"])
    if state.get("cuda_rng") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    return state["obs"]


def evaluate_saved(args):
    """--evaluate RUN_DIR: the saved deterministic actor on fresh episodes of the dense return."""
    run_dir, paths = args.evaluate, [os.path.join(args.evaluate, name) for name in ("model.pt", "checkpoint.pt")]
    path = next((p for p in paths if os.path.isfile(p)), None)
    if path is None or not os.path.isfile(os.path.join(run_dir, "config.json")):
        raise ConfigError(f"--evaluate {run_dir}: no config.json with model.pt or checkpoint.pt there")
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            config = json.load(f)
        saved = torch.load(path, map_location="cpu", weights_only=False)  # also a run made with --device cuda
        actor_state = saved["actor"] if path == paths[0] else saved["agent"]["actor"]
    except Exception as e:
        raise ConfigError(f"cannot read {path}: {first_line(e)}") from None
    torch.set_num_threads(args.threads)
    env = make_env(config["env"], args.seed, time_feature=config["time_feature"], absorbing=config["absorbing"])
    agent = TD3(env.observation_space.shape[0], env.action_space.shape[0], env.action_space.low,
                env.action_space.high, hidden=config["hidden"])
    try:
        agent.actor.load_state_dict(actor_state)
    except RuntimeError as e:  # config.json and the saved networks disagree (sizes, env)
        raise ConfigError(f"{path} does not fit {run_dir}/config.json: {first_line(e)}") from None
    returns = []
    for i in range(args.eval_episodes):
        episode = rollout(env, agent.act)
        returns.append(episode["episodic_return"])
        print(f"episode {i + 1}: return {returns[-1]:.1f}, length {len(episode['actions'])}")
    print(f"{config['env']}, {path}: mean return {np.mean(returns):.1f} +- {np.std(returns):.1f} "
          f"over {len(returns)} episodes (env seed {args.seed})")
    return 0


def save_model(run_dir, agent, disc, args):
    model = {"actor": agent.actor.state_dict(), "critic": agent.critic.state_dict(),
             "discriminator": disc.state_dict() if disc is not None else None,
             "env": args.env, "hidden": args.hidden, "time_feature": args.time_feature, "absorbing": args.absorbing}
    atomic_write(os.path.join(run_dir, "model.pt"), lambda f: torch.save(model, f))


if __name__ == "__main__":
    sys.exit(main())
