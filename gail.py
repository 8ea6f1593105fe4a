"""GAIL and POfD: the paper's on-policy baselines, TRPO learning from a discriminator reward.

    python gail.py --env Hopper-v5             # GAIL (Ho and Ermon 2016)
    python gail.py --env Hopper-v5 --pofd      # POfD (Kang, Jie and Feng 2018)

Each iteration collects --steps-per-batch env steps with the current Gaussian policy, trains
the discriminator D on-policy (teacher R_E labelled 1, this batch labelled 0; the discriminator,
its loss and its reward are discriminator.py's, as sail.py's), rewards every step with r'(s, a) = -log(1 - D(s, a)),
or for POfD with 0.1 r_e - log(1 - D(s, a)) where r_e is the sparse episodic reward, and takes
one TRPO step (Schulman et al. 2015): the policy gradient of the GAE advantages, turned into a
natural gradient by conjugate gradient on the KL's Hessian, scaled to the KL bound --max-kl and
shortened by a line search until the surrogate improves within the bound. A value network,
fitted by Adam, gives the advantages' baseline. Policy and value see observations normalised by
running statistics. The run folder, CSV columns, --resume and stopping are sail.py's.
"""

import os
import sys

import plumbing

if __name__ == "__main__":
    plumbing.quiet_interrupt_while_importing("gail.py")

import dataclasses
import math
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

from demos import default_demo_path, load_teacher_buffer
from discriminator import Discriminator, RunningNorm, discriminator_loss, shaped_reward
from envs import EnvState, evaluate_policy, make_env
from plumbing import PROGRESS_COLUMNS, non_negative_float, positive_int
from td3 import make_adam, mlp

RESUMABLE = ("total_timesteps", "threads")


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Walker2d-v5", help="gymnasium env id")
    p.add_argument("--pofd", action="store_true", help="POfD: add 0.1 x the sparse episodic reward to D's reward")
    p.add_argument("--seed", type=plumbing.seed, default=1, help="seed of env, action space, numpy and torch")
    p.add_argument("--total-timesteps", type=positive_int, default=1_000_000, help="env steps of the run")
    p.add_argument("--steps-per-batch", type=positive_int, default=5000, help="env steps per TRPO iteration")
    p.add_argument("--demos", help="demo file (default: demos/<env>.npz)")
    p.add_argument("--num-demos", type=positive_int, default=1, help="teacher episodes used from the demo file")
    p.add_argument("--hidden", type=positive_int, nargs="+", default=[100, 100], help="policy/value hidden sizes (tanh)")
    p.add_argument("--gamma", type=float, default=0.995, help="discount")
    p.add_argument("--gae-lambda", type=float, default=0.97, help="GAE lambda")
    p.add_argument("--max-kl", type=non_negative_float, default=0.01, help="KL bound of a TRPO step")
    p.add_argument("--cg-iters", type=positive_int, default=10, help="conjugate gradient iterations")
    p.add_argument("--cg-damping", type=non_negative_float, default=0.1, help="damping added to the KL's Hessian")
    p.add_argument("--backtracks", type=positive_int, default=10, help="line search halvings of the step")
    p.add_argument("--vf-lr", type=non_negative_float, default=1e-3, help="Adam learning rate of the value network")
    p.add_argument("--vf-epochs", type=positive_int, default=5, help="value network epochs per batch")
    p.add_argument("--vf-batch-size", type=positive_int, default=128, help="value network minibatch size")
    p.add_argument("--pofd-weight", type=non_negative_float, default=0.1, help="POfD: weight of r_e")
    p.add_argument("--disc-hidden", type=positive_int, nargs="+", default=[256, 256], help="D hidden sizes (tanh)")
    # one Adam step of D per batch, as OpenAI baselines' GAIL: more (5 epochs of 256-sample steps at 1e-3
    # were tried) lets D separate teacher and batch completely, and the reward -log(1 - D) vanishes
    p.add_argument("--disc-lr", type=non_negative_float, default=3e-4, help="D's Adam learning rate")
    p.add_argument("--disc-epochs", type=positive_int, default=1, help="D epochs over each batch")
    p.add_argument("--disc-batch-size", type=positive_int, help="teacher and own samples per D step "
                   "(default: the whole batch, --steps-per-batch)")
    # GAIL's own discriminator loss: no gradient penalty (SAIL's two-sided penalty of 10, with D
    # trained on each batch only, first pushed D's slope the wrong way: the policy followed it)
    p.add_argument("--grad-penalty", type=non_negative_float, default=0.0, help="D's gradient penalty weight")
    p.add_argument("--entropy-coef", type=non_negative_float, default=0.001, help="D's entropy bonus weight")
    p.add_argument("--eval-freq", type=positive_int, default=10_000, help="env steps between evaluations "
                   "(at the end of the batch that crosses them)")
    p.add_argument("--eval-episodes", type=positive_int, default=5, help="episodes per evaluation")
    p.add_argument("--threads", type=plumbing.threads, default=1, help="torch CPU threads")
    p.add_argument("--output-dir", default="runs", help="parent folder of the run folder")
    p.add_argument("--run-name", help="run folder name (default: <env>__<gail|pofd>__<seed>__<time>)")
    p.add_argument("--checkpoint-freq", type=positive_int, default=50_000, help="env steps between checkpoints")
    p.add_argument("--tensorboard", action="store_true", help="also log progress.csv's numbers to TensorBoard")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue the run saved in RUN_DIR with its flags "
                   "(only --total-timesteps and --threads may be given anew)")
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    args.given = p.given_flags(argv)
    if not (0.0 < args.gamma <= 1.0 and 0.0 <= args.gae_lambda <= 1.0):
        p.error("--gamma must be in (0, 1] and --gae-lambda in [0, 1]")
    if args.steps_per_batch < 2:
        p.error("--steps-per-batch must be at least 2: the advantages are normalised by their spread over the batch")
    if args.eval_freq > args.total_timesteps and not args.resume:
        p.error(f"--eval-freq {args.eval_freq} is more than --total-timesteps {args.total_timesteps}: "
                "the run would write no progress.csv")
    args.disc_batch_size = args.disc_batch_size or args.steps_per_batch
    if args.steps_per_batch < args.disc_batch_size:
        p.error("--steps-per-batch must be at least --disc-batch-size")
    plumbing.check_tensorboard(p, args)
    args.algo = "pofd" if args.pofd else "gail"
    args.method = "POfD" if args.pofd else "GAIL"  # what plot.py reads from config.json
    args.time_feature, args.absorbing = True, False  # the sparse setting's observations, as sail.py's
    return args


class GaussianPolicy(nn.Module):
    """pi(a|s) = N(mean(s), diag(std)^2): a tanh MLP for the mean, a state-independent log std."""

    def __init__(self, obs_dim, act_dim, hidden):
        super().__init__()
        self.mean = mlp([obs_dim, *hidden, act_dim], nn.Tanh)
        self.log_std = nn.Parameter(torch.zeros(act_dim))

    def forward(self, obs):
        return torch.distributions.Normal(self.mean(obs), self.log_std.exp())


# ---------------------------------------------------------------------------------------------
# TRPO (Schulman et al. 2015)
# ---------------------------------------------------------------------------------------------

def flat_grad(y, params, **kwargs):
    return torch.cat([g.reshape(-1) for g in torch.autograd.grad(y, params, **kwargs)])


def set_flat(params, flat):
    """Copies a flat vector into the parameters, in place (their storage, so their memory
    alignment and with it MKL's rounding, stays what it was: resumed runs stay exact)."""
    for p, values in zip(params, flat.split([p.numel() for p in params])):
        p.copy_(values.view_as(p))


def conjugate_gradient(matrix_vector, b, iters, tolerance=1e-10):
    """x with A x = b for a symmetric positive definite A given only as v -> A v."""
    x, r = torch.zeros_like(b), b.clone()
    p, rr = b.clone(), b @ b
    for _ in range(iters):
        Ap = matrix_vector(p)
        step = rr / (p @ Ap)
        x += step * p
        r -= step * Ap
        rr_new = r @ r
        if rr_new < tolerance:
            break
        p, rr = r + rr_new / rr * p, rr_new
    return x


def trpo_step(policy, obs, actions, advantages, max_kl, damping, cg_iters, backtracks):
    """One TRPO step: maximise the surrogate E[pi(a|s) / pi_old(a|s) A] s.t. KL(pi_old || pi) <= max_kl."""
    params = [p for p in policy.parameters()]
    with torch.no_grad():
        old = policy(obs)
        old_log_prob = old.log_prob(actions).sum(-1)

    def surrogate_and_kl():
        new = policy(obs)
        ratio = torch.exp(new.log_prob(actions).sum(-1) - old_log_prob)
        return (ratio * advantages).mean(), torch.distributions.kl_divergence(old, new).sum(-1).mean()

    surrogate, kl = surrogate_and_kl()
    gradient = flat_grad(surrogate, params, retain_graph=True)
    kl_gradient = flat_grad(kl, params, create_graph=True)

    def fisher_vector(v):  # (H_KL + damping I) v, the KL's Hessian times v, by double backward
        return flat_grad(kl_gradient @ v, params, retain_graph=True) + damping * v

    direction = conjugate_gradient(fisher_vector, gradient, cg_iters)
    # the largest step along `direction` whose quadratic KL estimate 0.5 s^T H s is max_kl
    step = direction * torch.sqrt(2 * max_kl / (direction @ fisher_vector(direction)).clamp_min(1e-12))
    old_params = torch.cat([p.detach().reshape(-1) for p in params])
    with torch.no_grad():
        for fraction in 0.5 ** np.arange(backtracks):
            set_flat(params, old_params + fraction * step)
            new_surrogate, new_kl = surrogate_and_kl()
            if new_kl <= max_kl and new_surrogate > surrogate:
                return {"actor_loss": -new_surrogate.item(), "kl": new_kl.item()}
        set_flat(params, old_params)  # no step passed: keep the old policy
    return {"actor_loss": -surrogate.item(), "kl": 0.0}


def gae(rewards, values, next_values, terminated, episode_end, gamma, lam):
    """Generalised advantage estimates over a batch of consecutive steps. A time-limit
    truncation bootstraps from V(s') like any step; only `terminated` zeroes the next value."""
    deltas = rewards + gamma * (1.0 - terminated) * next_values - values
    advantages, running = torch.zeros_like(rewards), 0.0
    for t in reversed(range(len(rewards))):
        running = deltas[t] + gamma * lam * (1.0 - episode_end[t]) * running
        advantages[t] = running
    return advantages


# ---------------------------------------------------------------------------------------------
# The loop
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass
class LoopState:
    global_step: int = 0
    iterations: int = 0
    train_episodic_return: float = float("nan")
    train_time: float = 0.0
    rows: list = dataclasses.field(default_factory=list)


def train(args):
    if args.resume:
        args = plumbing.resume_config(args.resume, args, args.given, RESUMABLE, "gail.py")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    env, eval_env = make_env(args.env, args.seed), make_env(args.env, args.seed + 100)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    low, high = env.action_space.low, env.action_space.high
    teacher_buffer = load_teacher_buffer(args.demos or default_demo_path(args.env), args.env, env, args.num_demos,
                                         10**9, time_feature=True, absorbing=False)
    policy, value = GaussianPolicy(obs_dim, act_dim, args.hidden), mlp([obs_dim, *args.hidden, 1], nn.Tanh)
    obs_norm = RunningNorm(obs_dim)  # for policy and value; D keeps its own
    disc = Discriminator(obs_dim, act_dim, args.disc_hidden)
    value_optimizer, disc_optimizer = make_adam(value.parameters(), args.vf_lr), make_adam(disc.parameters(), args.disc_lr)
    parts = {"policy": policy, "value": value, "obs_norm": obs_norm, "disc": disc, "value_optimizer": value_optimizer,
             "disc_optimizer": disc_optimizer, "env": EnvState(env), "eval_env": EnvState(eval_env),
             "rng": plumbing.RNGs(rng)}

    def act(obs, deterministic=False):
        with torch.no_grad():
            dist = policy(obs_norm(torch.as_tensor(obs, dtype=torch.float32)))
            return (dist.mean if deterministic else dist.sample()).numpy()

    with plumbing.StopRequest() as stop:
        if args.resume:
            run_dir = args.resume
            saved = plumbing.load_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts)
            s, obs = LoopState(**saved["loop"]), saved["obs"]
            plumbing.record_resume(run_dir, args, s.global_step, RESUMABLE)
        else:
            s, (obs, _) = LoopState(), env.reset()
            config = {k: v for k, v in vars(args).items() if k != "given"} | {"script": "gail.py"}
            run_dir = plumbing.make_run_dir(args.output_dir, args.run_name or plumbing.run_name(
                args.env, args.algo, args.seed), config)
        print(f"run folder: {run_dir}\nteacher: {plumbing.count(teacher_buffer.num_episodes, 'episode')}, return "
              f"{np.mean(teacher_buffer.returns):.1f}", flush=True)
        bar = tqdm(total=args.total_timesteps, initial=s.global_step, desc=f"{args.algo} {args.env}", unit="step",
                   dynamic_ncols=True, mininterval=1.0)
        log = plumbing.ProgressLog(run_dir, PROGRESS_COLUMNS, s.rows, args.tensorboard)
        clock, last_row = time.perf_counter(), (s.global_step, s.train_time)
        while s.global_step < args.total_timesteps and not stop.requested:
            # 1. a batch of env steps with the current policy; the env and RNG state at its start are
            #    what a checkpoint keeps, so that a batch cut short by a stop is collected again
            start = {name: parts[name].state_dict() for name in ("env", "rng")} | {"obs": obs}
            batch = {k: [] for k in ("obs", "actions", "env_actions", "rewards", "next_obs", "terminated", "end")}
            for _ in range(args.steps_per_batch):
                action = act(obs)
                env_action = np.clip(action, low, high).astype(np.float32)
                next_obs, reward, terminated, truncated, info = env.step(env_action)
                for k, v in zip(batch, (obs, action, env_action, reward, next_obs, terminated, terminated or truncated)):
                    batch[k].append(v)
                obs = next_obs
                if terminated or truncated:
                    s.train_episodic_return = float(info["episode"]["r"])
                    obs, _ = env.reset()
                if stop.requested:
                    break
            if stop.requested:
                for name in ("env", "rng"):
                    parts[name].load_state_dict(start[name])
                obs = start["obs"]
                break
            batch = {k: torch.as_tensor(np.array(v), dtype=torch.float32) for k, v in batch.items()}
            batch["end"][-1] = 1.0  # the batch's last step ends its advantage sums (it bootstraps from V(s'))
            s.global_step += args.steps_per_batch
            s.iterations += 1

            # 2. D on-policy, Eq. (4) of the SAIL paper: the teacher against this batch
            n = args.steps_per_batch
            for _ in range(args.disc_epochs):
                for idx in torch.randperm(n).split(args.disc_batch_size):
                    if len(idx) < args.disc_batch_size:
                        continue
                    t_obs, t_act, *_ = teacher_buffer.sample(len(idx))
                    disc.update_norms(torch.cat([t_obs, batch["obs"][idx]]),
                                      torch.cat([t_act, batch["env_actions"][idx]]))
                    loss, d_teacher, d_self = discriminator_loss(disc, t_obs, t_act, batch["obs"][idx],
                                                                 batch["env_actions"][idx], args.entropy_coef,
                                                                 args.grad_penalty)
                    disc_optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    disc_optimizer.step()

            # 3. rewards: -log(1 - D); POfD adds the sparse episodic reward r_e (nonzero at episode ends)
            rewards = shaped_reward(disc, batch["obs"], batch["env_actions"], "sail")
            if args.pofd:
                rewards = rewards + args.pofd_weight * batch["rewards"]

            # 4. advantages, the TRPO step, the value fit
            obs_norm.update(batch["obs"])
            norm_obs, norm_next = obs_norm(batch["obs"]), obs_norm(batch["next_obs"])
            with torch.no_grad():
                values, next_values = value(norm_obs).squeeze(-1), value(norm_next).squeeze(-1)
            advantages = gae(rewards, values, next_values, batch["terminated"], batch["end"], args.gamma,
                             args.gae_lambda)
            returns = advantages + values
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
            stats = trpo_step(policy, norm_obs, batch["actions"], advantages, args.max_kl, args.cg_damping,
                              args.cg_iters, args.backtracks)
            for _ in range(args.vf_epochs):
                for idx in torch.randperm(n).split(args.vf_batch_size):
                    value_loss = F.mse_loss(value(norm_obs[idx]).squeeze(-1), returns[idx])
                    value_optimizer.zero_grad(set_to_none=True)
                    value_loss.backward()
                    value_optimizer.step()
            stats |= {"disc_loss": loss.item(), "disc_teacher": d_teacher.item(), "disc_self": d_self.item(),
                      "reward_mean": rewards.mean().item(), "critic_loss": value_loss.item()}
            if not all(math.isfinite(v) for v in stats.values()):
                raise plumbing.ConfigError(f"non-finite loss {stats} at step {s.global_step}; stopped, the last "
                                           f"good checkpoint in {run_dir} is kept")
            bar.update(args.steps_per_batch)

            # 5. evaluation of the mean action, the CSV row, a checkpoint
            if s.global_step // args.eval_freq > (s.global_step - n) // args.eval_freq:
                now = time.perf_counter()
                s.train_time += now - clock
                mean_action = lambda o: np.clip(act(o, deterministic=True), low, high)  # noqa: E731
                row = {"global_step": s.global_step, **evaluate_policy(eval_env, mean_action, args.eval_episodes),
                       "train_episodic_return": s.train_episodic_return, "teacher_episodes": teacher_buffer.num_episodes,
                       "teacher_threshold": teacher_buffer.threshold, "updates": s.iterations, "time": s.train_time,
                       "steps_per_second": (s.global_step - last_row[0]) / max(s.train_time - last_row[1], 1e-9)}
                log.append({k: float("nan") for k in PROGRESS_COLUMNS} | {k: v for k, v in stats.items() if k in PROGRESS_COLUMNS}
                           | row)
                bar.set_postfix(eval=f"{row['eval_return']:.0f}", refresh=False)
                clock, last_row = time.perf_counter(), (s.global_step, s.train_time)
            if s.global_step // args.checkpoint_freq > (s.global_step - n) // args.checkpoint_freq:
                plumbing.save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts, loop=dataclasses.asdict(s),
                                         obs=obs)
        bar.close()
        s.train_time += time.perf_counter() - clock
        plumbing.save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts, loop=dataclasses.asdict(s), obs=obs)
    if stop.requested:
        print(f"stopped at step {s.global_step}: checkpoint saved, continue with --resume {run_dir}")
    return stop.exit_code


def main(argv=None):
    return plumbing.run_main("gail.py", train, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
