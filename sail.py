"""SAIL: Self-Adaptive Imitation Learning (Zhu, Lin, Dai, Zhou), in one file.

    python sail.py --env Walker2d-v5

The environment returns no per-step reward, only the episodic return r_e when an episode ends
(envs.py). The agent starts from one to four episodes of a sub-optimal teacher (demos/<env>.npz).
Algorithm 1 of the paper, as the loop in `train` runs it:

    input: teacher buffer R_E (the demos), self buffer R_B (random-policy steps), alpha = 0.5
    for each env step:
        act with the TD3 actor plus noise; R_B <- R_B + (s, a, s')
        if an episode tau just ended and r_e(tau) > min over R_E of r_e:  R_E <- R_E + tau
            (the whole episode), and anneal alpha -> 0
        update the discriminator D by Eq. (4): teacher R_E labelled 1, R_B labelled 0 (by
            default, once an episode has been promoted, R_B's most recent steps)
        update the critic by Eq. (7) and the actor by Eq. (8), on batches drawn from
            alpha R_E + (1 - alpha) R_B, with the reward r'(s, a) = -log(1 - D(s, a))
            plus the return bonus and the learned per-step reward (both below)

Equation numbers are the paper's: (4) the discriminator objective, (7) the critic's squared TD
error and (8) the deterministic policy gradient on the mixed batch. The paper's ablations are
flags (--fixed-alpha, --no-lfd, --no-adaptation, --on-policy-from start); DAC and TD3 on the
sparse reward are presets of the same loop (--algo dac, td3); behaviour cloning is bc.py.

sail.py's defaults add six things to the paper, each a flag that turns it off; the first five
together ended above the paper's SAIL with the return bonus alone in every same-seed pair we ran,
and the sixth was made a default by a grid whose rule was fixed before its runs (README's Results).
`--algo sail-paper` is the paper's SAIL, exactly.
- The return bonus (--return-bonus, beta = 1). D's reward only says "look like R_E", so once the
  agent does, only a lucky noisy episode that beats R_E's worst moves it on. The bonus credits
  every transition with its episode's return scaled to [0, 1] (IRCR's guidance reward,
  Gangwani et al. 2020), which tells the critic which of the agent's own episodes were better.
- The return decomposition (--return-decomposition, --decomposition-unit rate): a per-step
  reward r(s, a, s') learned so that its sum over an episode fits the episodic return (RRD,
  Ren et al. 2022), a credit that, unlike the bonus, differs between the steps of one episode.
- LayerNorm in the critics (--critic-layer-norm, as RLPD), against Q values that run away from
  the data on the large rewards of a learned D.
- An on-policy D once the agent improves on its teacher (--on-policy-disc, --on-policy-from
  promotion): after the first promotion D tells R_E from the agent's recent steps, not from all
  of R_B, whose old, poor steps it would keep rewarding the agent for being unlike.
- D's actions normalised as its states (--disc-action-norm), so that D sees how much control
  the agent spends and not only where it goes.
- A learned action cost (--decomposition-action-cost, --actor-action-cost): the decomposition's
  reward also subtracts c ||a||^2 with c >= 0 learned from the episodic returns, and the actor is
  charged that cost beside Q, whose slope in the action is too flat to carry it. Where control
  costs little, c falls to 0 and this is the five above.
All of them use only what the sparse env gives at an episode's end.
"""

import os
import signal
import sys

if __name__ == "__main__":  # Ctrl-C while torch loads: one line and exit 130, no traceback. os._exit,
    # since an exception raised in Python code that torch's C++ import calls aborts the process
    signal.signal(signal.SIGINT, lambda signum, frame: os._exit(print("sail.py: interrupted", file=sys.stderr, flush=True) or 130))

import argparse
import dataclasses
import math
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from tqdm import tqdm

import cpu_kernels
import plumbing
from buffers import ReplayBuffer, TeacherBuffer, default_demo_path, load_teacher_buffer, mixed_batch
from envs import EnvState, evaluate_policy, get_env_state, make_env, set_env_state
from evaluate import evaluate_run, save_model
from plumbing import ConfigError, non_negative_float, positive_int
from td3 import TD3, colored_noise, make_adam, mlp

# Presets of --algo: each sets defaults that explicit flags still override. sail.py's own defaults are
# SAIL with this repo's additions (the module docstring); the others keep the published methods'
# plain TD3 learner and off-policy D, whatever those defaults become.
PLAIN_LEARNER = {"critic_layer_norm": False, "on_policy_disc": False, "on_policy_from": "start",
                 "return_decomposition": 0.0, "decomposition_unit": "range", "disc_action_norm": False,
                 "decomposition_action_cost": False, "actor_action_cost": False}
PRESETS = {
    "sail": {},
    # the paper's SAIL, Algorithm 1 as published: none of this repo's additions
    "sail-paper": PLAIN_LEARNER | {"return_bonus": 0.0},
    # DAC (Kostrikov et al. 2019): absorbing states, AIRL-style reward, no mixing, no adaptation
    "dac": PLAIN_LEARNER | {"absorbing": True, "time_feature": False, "reward": "airl", "no_lfd": True,
                            "no_adaptation": True, "return_bonus": 0.0},
    # TD3 on the sparse episodic reward alone: no demos, no discriminator
    "td3": PLAIN_LEARNER | {"reward": "env", "no_lfd": True, "no_adaptation": True, "return_bonus": 0.0},
    # IRCR (Gangwani et al. 2020): TD3 on the return bonus alone (each step credited with its episode's
    # scaled return); no demos, no discriminator: what the bonus can learn without imitation
    "ircr": PLAIN_LEARNER | {"reward": "none", "no_lfd": True, "no_adaptation": True},
    # RRD (Ren et al. 2022): TD3 on a learned per-step reward whose sum over an episode fits its
    # episodic return; no demos, no discriminator
    "rrd": PLAIN_LEARNER | {"reward": "none", "no_lfd": True, "no_adaptation": True, "return_bonus": 0.0,
                            "return_decomposition": 1.0},
}
CSV_COLUMNS = ["global_step", "eval_return", "eval_return_std", "eval_length", "eval_return_actor", "eval_return_target",
               "train_episodic_return", "teacher_threshold", "teacher_episodes", "promotions", "alpha", "disc_loss",
               "disc_teacher", "disc_self", "reward_mean", "decomposition_loss",
               "decomposition_action_cost", "critic_loss", "actor_loss", "q",
               "updates", "steps_per_second", "time"]
# what --resume RUN_DIR may change; every other flag is the saved run's
RESUMABLE = ("total_timesteps", "threads", "device")
# a run saved before the return bonus existed (or became the default) ran without; and without decomposition
PREDATING = {"return_bonus": 0.0, "return_decomposition": 0.0, "critic_layer_norm": False,
             "decomposition_unit": "range", "decomposition_action_cost": False, "actor_action_cost": False,
             "n_step": 1, "utd": 1, "bc_weight": 0.0, "action_l2": 0.0, "action_budget": "none", "disc_action_norm": False, "noise_beta": 0.0,
             "contact_forces": True, "on_policy_from": "start"}


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = p.add_argument_group("experiment")
    g.add_argument("--env", default="Walker2d-v5", help="gymnasium env id (MuJoCo v5 or any Box-action env)")
    g.add_argument("--algo", choices=sorted(PRESETS), default="sail", help="method: SAIL or a baseline preset")
    g.add_argument("--seed", type=plumbing.seed, default=1, help="seed of env, action space, numpy and torch")
    g.add_argument("--total-timesteps", type=positive_int, default=1_000_000, help="env steps of the run")
    g.add_argument("--learning-starts", type=positive_int, default=10_000,
                   help="uniformly random steps that initialise R_B before any update (with the return bonus "
                   "or decomposition, also until an episode has ended and two different returns were seen)")
    g.add_argument("--eval-freq", type=positive_int, default=10_000, help="env steps between evaluations of the "
                   "deterministic policy")
    g.add_argument("--eval-episodes", type=positive_int, default=5, help="episodes per evaluation")
    g.add_argument("--demos", help="demo file (default: demos/<env>.npz)")
    g.add_argument("--num-demos", type=positive_int, default=1, help="teacher episodes used from the demo file")
    g.add_argument("--device", choices=["cpu", "cuda", "auto"], default="cpu", help="torch device")
    g.add_argument("--threads", type=plumbing.threads, default=2, help="torch CPU threads")
    g.add_argument("--kernels", choices=["auto", "torch", "onednn"], default="auto",
                   help="CPU matmul kernels (cpu_kernels.py); auto times both at start-up")
    g.add_argument("--output-dir", default="runs", help="parent folder of the run folder")
    g.add_argument("--run-name", help="run folder name (default: <env>__<algo>__<seed>__<time>)")
    g.add_argument("--save-model", action="store_true", help="save the networks to model.pt at the end")
    g.add_argument("--tensorboard", action="store_true", help="also log progress.csv's numbers as TensorBoard "
                   "scalars in the run folder (needs the tensorboard package)")
    g.add_argument("--resume", metavar="RUN_DIR", help="continue the run saved in RUN_DIR with its "
                   "flags (only --total-timesteps, --threads and --device may be given anew)")
    g.add_argument("--checkpoint-freq", type=positive_int, default=50_000, help="env steps between checkpoints")
    g.add_argument("--evaluate", metavar="RUN_DIR", help="only play --eval-episodes episodes of RUN_DIR's "
                   "saved actor (model.pt, else checkpoint.pt) on an env seeded with --seed")
    g.add_argument("--video", metavar="FILE", help="with --evaluate: render the episodes headless into FILE "
                   "(.gif, or .mp4 with imageio-ffmpeg)")
    g.add_argument("--eval-noise", type=non_negative_float, default=0.0, help="with --evaluate: the std of "
                   "Gaussian noise added to the actions, as --exploration-noise in training (0: deterministic)")
    g.add_argument("--deploy", choices=["actor", "target"], default="actor", help="the policy that eval_return "
                   "scores, model.pt holds and --evaluate plays: the actor or its Polyak-averaged target copy (with "
                   "--evaluate: the run's own unless given)")

    g = p.add_argument_group("TD3 learner")
    g.add_argument("--hidden", type=positive_int, nargs="+", default=[256, 256], help="actor/critic hidden sizes")
    g.add_argument("--lr", type=non_negative_float, default=3e-4, help="Adam learning rate of actor and critic")
    g.add_argument("--gamma", type=float, default=0.99, help="discount")
    g.add_argument("--tau", type=non_negative_float, default=0.005, help="Polyak averaging rate of target networks")
    g.add_argument("--batch-size", type=positive_int, default=256, help="critic/actor batch size")
    g.add_argument("--policy-noise", type=non_negative_float, default=0.2, help="target policy smoothing noise std")
    g.add_argument("--noise-clip", type=non_negative_float, default=0.5, help="target policy smoothing noise clip")
    g.add_argument("--policy-delay", type=positive_int, default=2, help="critic updates per actor update")
    g.add_argument("--exploration-noise", type=non_negative_float, default=0.1, help="std of Gaussian action noise")
    g.add_argument("--noise-beta", type=non_negative_float, default=0.0, help="color of the exploration noise: its "
                   "power spectrum along an episode falls as 1/f^beta (0: white, TD3's, each step independent; 1: "
                   "pink, Eberhard et al. 2023; 2: red), drawn anew for each episode")
    g.add_argument("--buffer-size", type=positive_int, default=1_000_000, help="capacity of R_B in transitions")
    g.add_argument("--n-step", type=positive_int, default=1, help="the critic's target sums the rewards of up to "
                   "N consecutive steps of the transition's episode before it bootstraps (n-step returns); 1 is TD3's")
    g.add_argument("--critic-layer-norm", action=argparse.BooleanOptionalAction, default=True, help="LayerNorm "
                   "before each hidden ReLU of the critics (as RLPD), against Q values that run away from the data")
    g.add_argument("--bc-weight", type=non_negative_float, default=0.0, help="behaviour cloning of R_E in the "
                   "actor's loss, as TD3+BC: Q over its mean magnitude plus this weight times the mean squared "
                   "distance to R_E's actions (TD3+BC's alpha 2.5 is 0.4); 0: off")
    g.add_argument("--action-l2", type=non_negative_float, default=0.0, help="quadratic penalty on the actor's "
                   "actions (per dimension, in units of half the action range) in its loss, weighed against Q over "
                   "its mean magnitude as --bc-weight is; 0: off")
    g.add_argument("--action-budget", choices=["none", "teacher"], default="none", help="what --action-l2 leaves "
                   "free: none, every action is penalised; teacher, only the batch's mean squared action above R_E's "
                   "(per step and dimension: the demos', then that of the best episodes that replace them), so the "
                   "actor may spend as much control as the best episodes seen but no more")
    g.add_argument("--update-every", type=positive_int, default=1,
                   help="env steps between groups of as many TD3 updates (authors: 1000)")
    g.add_argument("--utd", type=positive_int, default=1, help="update-to-data ratio: TD3 updates (and "
                   "reward-model minibatches) per env step, as RLPD raises it; 1 is TD3's")
    g.add_argument("--reward", choices=["sail", "airl", "env", "none"], default="sail",
                   help="critic reward: sail = -log(1-D), airl = log D - log(1-D), env = sparse env reward, "
                   "none = 0 (the return bonus or decomposition alone)")
    g.add_argument("--return-bonus", type=non_negative_float, default=1.0, help="adds this weight times the "
                   "episodic return of the transition's episode, scaled to [0, 1] (--return-scale), to the "
                   "critic reward (IRCR's guidance reward); 0: off, the paper's SAIL (dac, td3: 0)")
    g.add_argument("--return-scale", choices=["minmax", "rank"], default="minmax", help="how --return-bonus "
                   "scales an episodic return to [0, 1]: minmax = between the lowest and highest returns seen "
                   "(IRCR); rank = the share of R_B's finished transitions whose episode scored no higher")
    g.add_argument("--return-decomposition", type=non_negative_float, default=1.0, help="adds this weight times "
                   "a learned per-step reward r(s, a, s'), fitted so that an episode's steps sum to its episodic "
                   "return (randomized return decomposition, Ren et al. 2022), divided by --decomposition-unit, to "
                   "the critic reward; 0: off (sail-paper, dac, td3, ircr: 0)")
    g.add_argument("--decomposition-unit", choices=["range", "rate"], default="rate", help="what the learned "
                   "reward is divided by: range = the range of episodic returns seen over the env's time limit; rate "
                   "= the range of per-step returns (return / length) seen: the same where every episode runs to the "
                   "limit, a larger unit where episodes end early, where range's unit lets r outweigh D's reward")
    g.add_argument("--decomposition-action-cost", action=argparse.BooleanOptionalAction, default=True,
                   help="the learned reward also subtracts c ||a||^2, a quadratic action cost whose weight c >= 0 is "
                   "learned with it from the episodic returns (the form of gymnasium's control cost), which the "
                   "network alone learns only in part (off where --return-decomposition is 0)")
    g.add_argument("--actor-action-cost", action=argparse.BooleanOptionalAction, default=True, help="the actor's "
                   "loss also charges that learned cost, c ||a||^2 in the critic's reward unit, beside Q: its exact "
                   "slope in the action, which Q, nearly flat in the action, carries only in part (off where "
                   "--decomposition-action-cost is)")
    g.add_argument("--decomposition-subset", type=positive_int, default=64, help="steps drawn from each episode "
                   "per reward-model minibatch (RRD's K); --batch-size / K episodes per minibatch")
    g.add_argument("--time-feature", action=argparse.BooleanOptionalAction, default=True, help="append 1 - t/T to obs")
    g.add_argument("--absorbing", action=argparse.BooleanOptionalAction, default=False, help="DAC absorbing states")
    g.add_argument("--contact-forces", action=argparse.BooleanOptionalAction, default=True, help="keep the 78 "
                   "contact forces (cfrc_ext) in Ant-v5's observation, as gymnasium v5 does (Humanoid-v5 likewise); "
                   "--no-contact-forces drops them for every network, as Ant-v4's 27-dim default")

    g = p.add_argument_group("discriminator")
    g.add_argument("--disc-hidden", type=positive_int, nargs="+", default=[256, 256], help="hidden sizes (tanh)")
    g.add_argument("--disc-lr", type=non_negative_float, default=1e-3, help="Adam learning rate")
    g.add_argument("--disc-freq", type=positive_int, default=500, help="env steps between discriminator trainings")
    g.add_argument("--disc-steps", type=positive_int, default=10, help="minibatches per discriminator training")
    g.add_argument("--disc-batch-size", type=positive_int, default=256, help="teacher and self samples per minibatch")
    g.add_argument("--grad-penalty", type=non_negative_float, default=10.0, help="gradient penalty weight")
    g.add_argument("--entropy-coef", type=non_negative_float, default=0.01, help="Bernoulli entropy bonus weight")
    g.add_argument("--disc-action-norm", action=argparse.BooleanOptionalAction, default=True, help="normalise D's "
                   "actions as its states, by their running mean and variance (--no-disc-action-norm: the actions as "
                   "they are, as the paper, which D, under the gradient penalty, hardly looks at)")

    g = p.add_argument_group("SAIL and its ablations")
    g.add_argument("--alpha", type=float, default=0.5, help="initial share of teacher samples in batches")
    g.add_argument("--alpha-anneal-steps", type=int, default=0,
                   help="after the first promotion, anneal alpha linearly to 0 over this many steps "
                        "(0: switch at once, as the authors' code)")
    g.add_argument("--teacher-capacity", type=positive_int, default=10_000, help="capacity of R_E in transitions")
    g.add_argument("--fixed-alpha", action="store_true", help="ablation: alpha stays at --alpha")
    g.add_argument("--no-lfd", action="store_true", help="ablation: alpha = 0 always (no teacher samples)")
    g.add_argument("--no-adaptation", action="store_true", help="ablation: R_E is never updated")
    g.add_argument("--on-policy-disc", action=argparse.BooleanOptionalAction, default=True,
                   help="D's negatives are the most recent samples, not the whole R_B, from --on-policy-from on "
                        "(--no-on-policy-disc: the whole R_B always, as the paper's SAIL)")
    g.add_argument("--on-policy-window", type=positive_int, default=2_000,
                   help="recent transitions that --on-policy-disc draws negatives from")
    g.add_argument("--on-policy-from", choices=["start", "promotion"], default="promotion",
                   help="when --on-policy-disc starts: from the first promotion, before which D sees the whole R_B "
                        "as the paper's SAIL; or from the start (the paper's on-policy ablation)")

    argv = sys.argv[1:] if argv is None else argv
    p.set_defaults(**PRESETS[p.parse_known_args(argv)[0].algo])
    args = p.parse_args(argv)
    args.given = p.given_flags(argv)
    check_args(p, args)
    plumbing.check_tensorboard(p, args)
    return args


def check_args(p, args):
    """What a single flag's type cannot check (counts and rates are checked by their types)."""
    if args.alpha_anneal_steps < 0:
        p.error(f"--alpha-anneal-steps must be >= 0, got {args.alpha_anneal_steps}")
    if not 0.0 <= args.alpha <= 1.0:
        p.error(f"--alpha must be in [0, 1], got {args.alpha}")
    if not 0.0 < args.gamma <= 1.0:
        p.error(f"--gamma must be in (0, 1], got {args.gamma}")
    if args.reward in ("env", "none") and not (args.no_lfd and args.no_adaptation):
        p.error(f"--reward {args.reward} learns without demos: it needs --no-lfd and --no-adaptation "
                f"(or --algo {'td3' if args.reward == 'env' else 'ircr'})")
    if args.reward == "none" and args.return_bonus <= 0 and args.return_decomposition <= 0:
        p.error("--reward none leaves the critic only the return bonus or decomposition: give --return-bonus > 0 "
                "or --return-decomposition > 0")
    if "on_policy_from" in args.given and not args.on_policy_disc:
        p.error(f"--on-policy-from {args.on_policy_from} goes with --on-policy-disc")
    if args.bc_weight > 0 and args.reward not in ("sail", "airl"):
        p.error(f"--bc-weight clones R_E's actions: --reward {args.reward} learns without demos")
    if args.action_budget != "none" and not (args.action_l2 > 0 and args.reward in ("sail", "airl")):
        p.error(f"--action-budget {args.action_budget} is what --action-l2 leaves free: it needs --action-l2 > 0 "
                "and demos (not --reward env or none)")
    # the learned action cost is part of the decomposition: a default that has nothing to act on turns off
    # with it; asked for by name, it is an error
    if args.decomposition_action_cost and args.return_decomposition <= 0:
        if "decomposition_action_cost" in args.given:
            p.error("--decomposition-action-cost is part of the learned reward: it needs --return-decomposition > 0")
        args.decomposition_action_cost = False
    if args.actor_action_cost and not args.decomposition_action_cost:
        if "actor_action_cost" in args.given:
            p.error("--actor-action-cost charges the learned action cost: it needs --decomposition-action-cost")
        args.actor_action_cost = False
    if args.return_decomposition > 0 and args.decomposition_subset > args.batch_size:
        p.error(f"--decomposition-subset {args.decomposition_subset} is more than --batch-size {args.batch_size}")
    if args.buffer_size < 1001:
        p.error("--buffer-size must hold at least one whole episode (1001 transitions)")
    if args.eval_freq > args.total_timesteps and not (args.resume or args.evaluate):
        p.error(f"--eval-freq {args.eval_freq} is more than --total-timesteps {args.total_timesteps}: "
                "the run would write no progress.csv")
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: no CUDA device is available")
    if (args.video or args.eval_noise) and not args.evaluate:
        p.error(f"{'--video' if args.video else '--eval-noise'} goes with --evaluate RUN_DIR")


# ---------------------------------------------------------------------------------------------
# The discriminator (paper, "Off-Policy Adversarial TD Learning")
# ---------------------------------------------------------------------------------------------

class RunningNorm(nn.Module):
    """Normalises observations by the running mean and variance of the data seen so far
    (variance floor 1e-2, clipped to +-5), as in the authors' code."""

    def __init__(self, dim):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("var", torch.ones(dim))
        self.register_buffer("count", torch.tensor(1e-4))

    def update(self, x):
        """Parallel mean/variance update (Chan et al.) with a batch."""
        n, mean, var = len(x), x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.mean += delta * n / total
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.count.copy_(total)

    def forward(self, x):
        return ((x - self.mean) / self.var.clamp_min(1e-2).sqrt()).clamp(-5.0, 5.0)


class Discriminator(nn.Module):
    """D(s, a) = sigmoid(logit(s, a)): teacher buffer -> 1, self buffer -> 0, on normalised s (and,
    with `action_norm`, normalised a)."""

    def __init__(self, obs_dim, act_dim, hidden, action_norm=False):
        super().__init__()
        self.net = mlp([obs_dim + act_dim, *hidden, 1], nn.Tanh)
        self.obs_norm = RunningNorm(obs_dim)  # updated with the data D is trained on
        # Actions as they are sit beside states of unit variance, and under the gradient penalty D then
        # hardly looks at them (results/probe.py); on the same scale they weigh as much as the states
        self.act_norm = RunningNorm(act_dim) if action_norm else None

    def inputs(self, obs, actions):
        return torch.cat([self.obs_norm(obs), actions if self.act_norm is None else self.act_norm(actions)], dim=-1)

    def update_norms(self, obs, actions):
        self.obs_norm.update(obs)
        if self.act_norm is not None:
            self.act_norm.update(actions)

    def forward(self, x):
        """Logit of D for normalised inputs x = inputs(obs, actions)."""
        return self.net(x).squeeze(-1)


def discriminator_loss(disc, teacher_obs, teacher_act, self_obs, self_act, entropy_coef, grad_penalty):
    """Eq. (4) as a cross-entropy to minimise, minus an entropy bonus, plus a gradient penalty."""
    x_teacher, x_self = disc.inputs(teacher_obs, teacher_act), disc.inputs(self_obs, self_act)
    logits = disc(torch.cat([x_teacher, x_self]))
    labels = torch.cat([torch.ones(len(x_teacher)), torch.zeros(len(x_self))]).to(logits.device)
    bce = F.binary_cross_entropy_with_logits(logits, labels)
    entropy = torch.distributions.Bernoulli(logits=logits).entropy().mean()  # against a saturated D
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


def train_discriminator(disc, disc_optimizer, teacher_buffer, self_buffer, args, recent=False):
    """--disc-steps minibatches of Eq. (4): R_E labelled 1, R_B (or, `recent`, its recent part) 0."""
    device = disc.obs_norm.mean.device
    for _ in range(args.disc_steps):
        t_obs, t_act, _, _ = teacher_buffer.sample(args.disc_batch_size)
        if recent:
            b_obs, b_act, *_ = self_buffer.sample_recent(args.disc_batch_size, args.on_policy_window)
        else:
            b_obs, b_act, *_ = self_buffer.sample(args.disc_batch_size)
        t_obs, t_act, b_obs, b_act = (x.to(device) for x in (t_obs, t_act, b_obs, b_act))
        disc.update_norms(torch.cat([t_obs, b_obs]), torch.cat([t_act, b_act]))
        loss, d_teacher, d_self = discriminator_loss(disc, t_obs, t_act, b_obs, b_act,
                                                     args.entropy_coef, args.grad_penalty)
        disc_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        disc_optimizer.step()
    return {"disc_loss": loss.detach(), "disc_teacher": d_teacher.detach(), "disc_self": d_self.detach()}


def scale_returns(returns, kind, return_range, sorted_returns):
    """Episodic returns mapped to [0, 1] for --return-bonus. minmax: by the lowest and highest
    returns seen, as IRCR. rank: by the share of R_B's finished transitions whose episode scored
    no higher (`sorted_returns`), which a few very bad early episodes cannot flatten."""
    if kind == "rank":
        return torch.searchsorted(sorted_returns, returns, right=True) / len(sorted_returns)
    low, high = return_range
    return (returns - low) / max(high - low, 1e-8)


# ---------------------------------------------------------------------------------------------
# Return decomposition (an addition to the paper, on by default: --return-decomposition 0 turns it off)
# ---------------------------------------------------------------------------------------------

class RewardModel(nn.Module):
    """r(s, a, s'), a per-step reward learned from episodic returns alone (RRD, Ren et al. 2022;
    inputs s, a and the change of state, as in github.com/Stilwell-Git/Randomized-Return-Decomposition).

    With `learn_action_cost`, minus a learned quadratic cost of the action, c ||a||^2 with c >= 0, the form
    of the control cost in gymnasium's locomotion rewards. The network alone, fitted to episode sums,
    learns only a fraction of what actions cost (it reads a large action as the speed it makes); the
    explicit term lets the returns' differences set c. c starts near 0 (0.0025) and stays there where
    the returns do not ask for it."""

    # Adam moves a parameter by at most its step size per minibatch, and c's parameter has about 5 to go on
    # Ant-v5 (c from 0.0025 to 0.4): 17k minibatches at the networks' 3e-4 at the fastest, several times
    # that with the noisy gradients of one scalar
    ACTION_COST_LR = 1e-2

    def __init__(self, obs_dim, act_dim, hidden, learn_action_cost=False):
        super().__init__()
        self.net = mlp([2 * obs_dim + act_dim, *hidden, 1], nn.ReLU)
        self.register_parameter("action_cost_rho", nn.Parameter(torch.tensor(-6.0)) if learn_action_cost else None)

    def action_cost(self):
        """c = softplus(rho) >= 0, the weight of the squared action norm (0 without `learn_action_cost`)."""
        if self.action_cost_rho is None:
            return self.net[0].weight.new_zeros(())
        return F.softplus(self.action_cost_rho)

    def parameter_groups(self, lr):
        """Adam's parameter groups: the network at `lr`, c's parameter at ACTION_COST_LR."""
        groups = [{"params": list(self.net.parameters()), "lr": lr}]
        if self.action_cost_rho is not None:
            groups.append({"params": [self.action_cost_rho], "lr": self.ACTION_COST_LR})
        return groups

    def forward(self, obs, actions, next_obs):
        reward = self.net(torch.cat([obs, actions, next_obs - obs], dim=-1)).squeeze(-1)
        if self.action_cost_rho is not None:
            reward = reward - self.action_cost() * actions.pow(2).sum(-1)
        return reward


def train_reward_model(reward_model, optimizer, self_buffer, args):
    """One minibatch of randomized return decomposition: for a few finished episodes of R_B, the
    mean of r over K random steps (an unbiased estimate of the mean over all steps) is fitted to
    the episodic return over the episode's length (RRD's loss, per step). The subset's variance
    in the loss pulls r towards the same value within an episode, less so as K nears its length."""
    device = next(reward_model.parameters()).device
    num_episodes = max(1, args.batch_size // args.decomposition_subset)
    obs, actions, next_obs, mask, returns, lengths = (
        x.to(device) for x in self_buffer.sample_episode_subsets(num_episodes, args.decomposition_subset))
    per_step = reward_model(obs, actions, next_obs)
    estimate = (per_step * mask).sum(1) / mask.sum(1).clamp_min(1.0)
    loss = F.mse_loss(estimate, returns / lengths.clamp_min(1))
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    stats = {"decomposition_loss": loss.detach()}
    if reward_model.action_cost_rho is not None:
        stats["decomposition_action_cost"] = reward_model.action_cost().detach()
    return stats


def decomposition_unit(kind, return_range, rate_range, episode_steps):
    """The learned reward's unit: about 1 per step of the best episode seen over the worst."""
    if kind == "rate":
        return max(rate_range[1] - rate_range[0], 1e-8)
    return max(return_range[1] - return_range[0], 1e-8) / episode_steps


def teacher_action_budget(teacher_buffer, actor):
    """R_E's mean squared action per step and dimension, in units of half the action range
    (--action-budget teacher; again after each promotion, so that the budget grows only with
    episodes whose return paid for their control)."""
    actions = torch.cat([data[1] for _, data in teacher_buffer.episodes]).to(actor.action_bias.device)
    return float(actor.in_half_ranges(actions).pow(2).mean())


def td3_update(agent, disc, teacher_buffer, self_buffer, alpha, args, return_range=None, sorted_returns=None,
               reward_model=None, decomposition_unit=1.0, action_budget=0.0):
    """Eqs. (7) and (8): one TD3 step on a batch from alpha R_E + (1 - alpha) R_B, rewarded by D."""
    batch, env_rewards, mask, episode_returns = mixed_batch(teacher_buffer, self_buffer, args.batch_size, alpha,
                                                            with_returns=args.return_bonus > 0, n_step=args.n_step)
    # each row: up to --n-step consecutive steps of one episode (one step by default), flattened to
    # (rows x steps, dim) for the reward networks
    obs, actions, next_obs, terminated, mask = (x.to(agent.device) for x in (*batch, mask))
    steps = lambda x: x.flatten(0, 1)  # noqa: E731
    if args.reward == "env":  # the TD3-sparse baseline: the env's own (sparse episodic) reward
        rewards = env_rewards.to(agent.device)
    elif args.reward == "none":  # IRCR: the return bonus below is the whole reward
        rewards = torch.zeros_like(mask)
    else:
        rewards = shaped_reward(disc, steps(obs), steps(actions), args.reward).view_as(mask)
    if args.return_bonus > 0:
        # IRCR (Gangwani et al. 2020): every step of an episode is credited with the episode's
        # return, so the critic learns which actions lead to better episodes, beyond imitating R_E
        rewards = rewards + args.return_bonus * scale_returns(episode_returns.to(agent.device), args.return_scale,
                                                              return_range, sorted_returns)[:, None]
    if args.return_decomposition > 0:
        # RRD's learned per-step reward in units of the per-step returns seen (decomposition_unit), so
        # that its weight means the same whatever the env's reward scale
        with torch.no_grad():
            learned = reward_model(steps(obs), steps(actions), steps(next_obs)).view_as(mask)
        rewards = rewards + args.return_decomposition * learned / decomposition_unit
    # n-step return: the discounted rewards of the row's steps inside its episode, then the critic
    # bootstraps from the last of them, gamma^m on for m steps (uncorrected for the policy's change
    # since the steps were taken, as D4PG and Rainbow); m = 1 is Eq. (7)'s one-step target
    n_step_return = (rewards * mask * args.gamma ** torch.arange(args.n_step, device=agent.device)).sum(1)
    last = mask.sum(1).long() - 1
    rows = torch.arange(len(last), device=agent.device)
    next_obs, terminated = next_obs[rows, last], terminated[rows, last]
    # DAC: the absorbing state's only action is zero (as the agent and the demos act there, and as
    # in DAC's code). With the actor's action instead, the critic is asked for Q at actions it never
    # saw in that state, the actor pushes them up, and the self-loop multiplies that by 1/(1 - gamma).
    next_action_mask = 1.0 - next_obs[:, -1:] if args.absorbing else None
    bc = None
    if args.bc_weight > 0:
        # behaviour cloning of R_E: the teacher's actions, then those of the agent's best episodes once promoted,
        # so that the actor stays near the best behaviour seen while Q pulls it beyond
        teacher_obs, teacher_actions = (x.to(agent.device) for x in teacher_buffer.sample(args.batch_size)[:2])
        bc = (teacher_obs, teacher_actions, args.bc_weight)
    # the learned control cost c ||a||^2 as the critic's reward carries it, charged to the actor directly
    action_cost = (args.return_decomposition * reward_model.action_cost().detach() / decomposition_unit
                   if args.actor_action_cost else 0.0)
    losses = agent.update(obs[:, 0], actions[:, 0], n_step_return, next_obs, terminated, next_action_mask,
                          discount=args.gamma ** (last + 1.0), bc=bc, action_l2=args.action_l2,
                          action_budget=action_budget, action_cost=action_cost)
    return losses | {"reward_mean": rewards[:, 0].mean()}


# ---------------------------------------------------------------------------------------------
# The loop of Algorithm 1
# ---------------------------------------------------------------------------------------------

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
    rate_range: tuple = (float("inf"), -float("inf"))    # the same for return / length (--decomposition-unit rate)
    action_budget: float = 0.0          # R_E's mean squared action (--action-budget teacher), else 0
    train_time: float = 0.0             # seconds of training (evaluations excluded)
    rows: list = dataclasses.field(default_factory=list)  # progress.csv


def train(args):
    if args.resume:
        args = plumbing.resume_config(args.resume, args, args.given, RESUMABLE, PREDATING)
    device = torch.device("cuda" if args.device == "cuda" or (args.device == "auto" and torch.cuda.is_available())
                          else "cpu")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    env_options = {"time_feature": args.time_feature, "absorbing": args.absorbing, "contact_forces": args.contact_forces}
    env = make_env(args.env, args.seed, **env_options)
    eval_env = make_env(args.env, args.seed + 100, **env_options)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]

    # R_E: the teacher's episodes (none for TD3 on the sparse reward)
    use_demos = args.reward in ("sail", "airl")  # D's reward needs R_E; the env's and IRCR's do not
    teacher_buffer = (load_teacher_buffer(args.demos or default_demo_path(args.env), args.env, env, args.num_demos,
                                          args.teacher_capacity, args.time_feature, args.absorbing)
                      if use_demos else TeacherBuffer(args.teacher_capacity))

    agent = TD3(obs_dim, act_dim, env.action_space.low, env.action_space.high, hidden=args.hidden, lr=args.lr,
                gamma=args.gamma, tau=args.tau, policy_noise=args.policy_noise, noise_clip=args.noise_clip,
                policy_delay=args.policy_delay, device=device, critic_layer_norm=args.critic_layer_norm)
    self_buffer = ReplayBuffer(obs_dim, act_dim, args.buffer_size)
    disc = Discriminator(obs_dim, act_dim, args.disc_hidden, args.disc_action_norm).to(device)
    disc_optimizer = make_adam(disc.parameters(), args.disc_lr)
    # what a checkpoint holds besides the loop's state: each part has state_dict / load_state_dict
    parts = {"agent": agent, "disc": disc, "disc_optimizer": disc_optimizer, "self_buffer": self_buffer,
             "teacher_buffer": teacher_buffer, "env": EnvState(env), "eval_env": EnvState(eval_env),
             "rng": plumbing.RNGs(rng)}
    reward_model = None
    if args.return_decomposition > 0:
        reward_model = RewardModel(obs_dim, act_dim, args.hidden, args.decomposition_action_cost).to(device)
        reward_optimizer = make_adam(reward_model.parameter_groups(args.lr), args.lr)
        parts |= {"reward_model": reward_model, "reward_optimizer": reward_optimizer}

    # From here on Ctrl-C and SIGTERM only set stop.requested: the loop then stops between two
    # steps and checkpoints (during setup, before its first step), and the run can be resumed.
    with plumbing.StopRequest() as stop:
        if args.resume:
            run_dir = args.resume
            saved = plumbing.load_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts)
            s, obs, stats = LoopState(**saved["loop"]), saved["obs"], dict(saved.get("stats", {}))
            episode_noise = saved.get("episode_noise")
            plumbing.record_resume(run_dir, args, s.global_step, RESUMABLE)
        else:
            kernels = cpu_kernels.choose(args.kernels, [agent.actor.net, agent.critic.q1.net, disc.net],
                                         args.batch_size, device)
            s = LoopState(alpha=0.0 if args.no_lfd else args.alpha, kernels=kernels)
            if use_demos:
                s.return_range = (min(teacher_buffer.returns), max(teacher_buffer.returns))
                rates = [ret / len(data[0]) for ret, data in teacher_buffer.episodes]
                s.rate_range = (min(rates), max(rates))
            if args.action_budget == "teacher":
                s.action_budget = teacher_action_budget(teacher_buffer, agent.actor)
            obs, _ = env.reset()
            episode_noise = None
            stats = {}  # the latest losses, logged at each evaluation
            config = {k: v for k, v in vars(args).items() if k != "given"}
            run_dir = plumbing.make_run_dir(args.output_dir, args.run_name or plumbing.run_name(
                args.env, args.algo, args.seed), config)
        cpu_kernels.apply(s.kernels, [*agent.networks(), disc, *([reward_model] if reward_model else [])])
        ranked = args.return_bonus > 0 and args.return_scale == "rank"  # kept sorted, for scale_returns
        sorted_returns = None
        if ranked:  # as of the last episode's end: a resumed run takes the saved one (R_B may have wrapped since)
            sorted_returns = saved.get("sorted_returns") if args.resume else None
            if sorted_returns is None:
                sorted_returns = self_buffer.sorted_episode_returns()
            sorted_returns = sorted_returns.to(device)
        needs_returns = args.return_bonus > 0 or args.return_decomposition > 0

        def draw_episode_noise():
            """Colored exploration noise for a whole episode (white noise is drawn step by step)."""
            return colored_noise(args.noise_beta, env.max_episode_steps, act_dim, rng) if args.noise_beta > 0 else None
        if episode_noise is None:
            episode_noise = draw_episode_noise()

        def learning(step):
            """After the warm-up. Where the return bonus or decomposition is on, it also waits for an
            episode of its own to end and for two different returns seen (R_E's count), since both
            scale by their range (an env whose episodes outlast --learning-starts)."""
            return step >= args.learning_starts and not (needs_returns and (
                math.isnan(s.train_episodic_return) or s.return_range[0] >= s.return_range[1]))
        was_learning = learning(s.global_step)

        def count_time():  # training seconds since the last call (evaluations are not counted)
            nonlocal clock
            now = time.perf_counter()
            s.train_time, clock = s.train_time + now - clock, now

        def save_checkpoint():
            count_time()  # so that a run resumed from this checkpoint loses no training time
            # the latest losses too: D trains every --disc-freq steps, and the next evaluation logs them
            plumbing.save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts, loop=dataclasses.asdict(s), obs=obs,
                                     stats={k: float(v) for k, v in stats.items()}, episode_noise=episode_noise,
                                     sorted_returns=None if sorted_returns is None else sorted_returns.cpu())

        print(f"run folder: {run_dir}\nCPU: {plumbing.cpu_model()}, kernels: {s.kernels}", flush=True)
        if use_demos:
            print(f"teacher: {teacher_buffer.num_episodes} episodes, return {np.mean(teacher_buffer.returns):.1f}",
                  flush=True)
        log = plumbing.ProgressLog(run_dir, CSV_COLUMNS, s.rows, args.tensorboard)
        bar = tqdm(total=args.total_timesteps, initial=s.global_step, desc=f"{args.algo} {args.env}",
                   unit="step", dynamic_ncols=True, mininterval=1.0)
        clock, last_row = time.perf_counter(), (s.global_step, s.train_time)
        while s.global_step < args.total_timesteps and not stop.requested:
            s.global_step += 1

            # 1. act: uniformly random while R_B is initialised, then the actor plus Gaussian noise
            if not learning(s.global_step - 1):
                action = env.action_space.sample()
            else:
                step_of_episode = (self_buffer.ptr - s.episode_start) % args.buffer_size
                action = agent.explore(obs, args.exploration_noise, rng, None if episode_noise is None
                                       else episode_noise[min(step_of_episode, len(episode_noise) - 1)])
            if args.absorbing and obs[-1] == 1.0:  # the absorbing state: a zero action, as in the demos
                action = np.zeros(act_dim, np.float32)
            next_obs, reward, terminated, truncated, info = env.step(action)
            self_buffer.add(obs, action, reward, next_obs, terminated)
            obs = next_obs

            # 2. adaptive teacher buffer: a whole episode better than the worst teacher one joins R_E
            if terminated or truncated:
                s.train_episodic_return = float(info["episode"]["r"])
                self_buffer.end_episode(s.episode_start, s.train_episodic_return)
                if ranked:
                    sorted_returns = self_buffer.sorted_episode_returns().to(device)
                s.return_range = (min(s.return_range[0], s.train_episodic_return),
                                  max(s.return_range[1], s.train_episodic_return))
                rate = s.train_episodic_return / ((self_buffer.ptr - s.episode_start) % args.buffer_size or args.buffer_size)
                s.rate_range = (min(s.rate_range[0], rate), max(s.rate_range[1], rate))
                if not args.no_adaptation:
                    episode = self_buffer.latest((self_buffer.ptr - s.episode_start) % args.buffer_size)
                    if teacher_buffer.promote(s.train_episodic_return, *episode):
                        s.promotions += 1
                        if args.action_budget == "teacher":
                            s.action_budget = teacher_action_budget(teacher_buffer, agent.actor)
                        if s.first_promotion_step is None:
                            s.first_promotion_step = s.global_step
                obs, _ = env.reset()
                s.episode_start = self_buffer.ptr
                episode_noise = draw_episode_noise()

            # dynamic alpha: args.alpha until the first promotion, then 0 (at once or annealed)
            if not (args.fixed_alpha or args.no_lfd) and s.first_promotion_step is not None:
                done = (s.global_step - s.first_promotion_step) / max(args.alpha_anneal_steps, 1)
                s.alpha = args.alpha * max(0.0, 1.0 - done) if args.alpha_anneal_steps else 0.0

            if learning(s.global_step):
                # 3. discriminator, Eq. (4): teacher samples vs the whole R_B (off-policy), or recent ones
                if use_demos and (not was_learning or (s.global_step - args.learning_starts) % args.disc_freq == 0):
                    recent = args.on_policy_disc and (args.on_policy_from == "start" or s.first_promotion_step is not None)
                    stats.update(train_discriminator(disc, disc_optimizer, teacher_buffer, self_buffer, args, recent))
                was_learning = True

                # 4. TD3 on the mixture alpha R_E + (1 - alpha) R_B, rewarded by r'(s, a): Eqs. (7), (8)
                if s.global_step % args.update_every == 0:
                    unit = decomposition_unit(args.decomposition_unit, s.return_range, s.rate_range,
                                              env.max_episode_steps)
                    for _ in range(args.update_every * args.utd):
                        if reward_model is not None:
                            stats.update(train_reward_model(reward_model, reward_optimizer, self_buffer, args))
                        stats.update(td3_update(agent, disc, teacher_buffer, self_buffer, s.alpha, args,
                                                s.return_range, sorted_returns, reward_model, unit,
                                                s.action_budget))
                    bad = {k: float(v) for k, v in stats.items() if not math.isfinite(float(v))}
                    if bad:  # stop before a diverged actor acts in the env; the last checkpoint stays good
                        bar.close()
                        raise ConfigError(f"non-finite loss {bad} at step {s.global_step}; stopped, the last "
                                          f"good checkpoint in {run_dir} is kept")

            # 5. evaluation of the deterministic policy, the CSV row, a checkpoint
            if s.global_step % args.eval_freq == 0:
                count_time()
                # Both the actor and its Polyak-averaged target copy (an average over ~1/tau updates), on
                # the same start states; the target first, so the eval env ends where one evaluation leaves it
                start = get_env_state(eval_env)
                target = evaluate_policy(eval_env, lambda o: agent.act(o, target=True), args.eval_episodes)
                set_env_state(eval_env, start)
                actor = evaluate_policy(eval_env, agent.act, args.eval_episodes)
                row = {"global_step": s.global_step, **(target if args.deploy == "target" else actor),
                       "eval_return_actor": actor["eval_return"], "eval_return_target": target["eval_return"],
                       "train_episodic_return": s.train_episodic_return,
                       "teacher_threshold": teacher_buffer.threshold if use_demos else float("nan"),
                       "teacher_episodes": teacher_buffer.num_episodes, "promotions": s.promotions,
                       "alpha": s.alpha, "updates": agent.num_updates, "time": s.train_time,
                       "steps_per_second": (s.global_step - last_row[0]) / max(s.train_time - last_row[1], 1e-9)}
                row |= {k: float(stats[k]) if k in stats else float("nan") for k in CSV_COLUMNS if k not in row}
                log.append(row)
                bar.set_postfix(eval=f"{row['eval_return']:.0f}", threshold=f"{row['teacher_threshold']:.0f}",
                                alpha=s.alpha, refresh=False)
                clock, last_row = time.perf_counter(), (s.global_step, s.train_time)  # the evaluation's time left out
            if s.global_step % args.checkpoint_freq == 0:
                save_checkpoint()
            bar.update(1)
        bar.close()
        save_checkpoint()
    if args.save_model:
        save_model(run_dir, agent, disc, args)
    if stop.requested:
        print(f"stopped at step {s.global_step}: checkpoint saved, continue with --resume {run_dir}")
    return stop.exit_code


def main(argv=None):
    args = parse_args(argv)
    if args.evaluate:
        return plumbing.run_main("sail.py", lambda a: evaluate_run(
            a.evaluate, a.eval_episodes, a.seed, a.threads, a.video, a.eval_noise,
            a.deploy if "deploy" in a.given else None), args)
    return plumbing.run_main("sail.py", train, args)


if __name__ == "__main__":
    sys.exit(main())
