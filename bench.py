"""Speed of SAIL's training against a plain CleanRL-style TD3 loop, measured side by side.

    python bench.py                      # Walker2d-v5 sizes, 1 and 2 threads, a few minutes
    python bench.py --threads 1 --breakdown

What it measures, each on the CPU at hand (its model printed first):
  1. the compute limit: GFLOP/s of a float32 matmul of the networks' size (--hidden: 256x256x256),
     through torch.mm (MKL) and through oneDNN (cpu_kernels.linear), and the FLOPs of one update of
     the paper's SAIL;
  2. updates on the same random data: the plain TD3 update against the paper's SAIL update (TD3
     step, discriminator reward of the batch, discriminator training amortised over --disc-freq),
     with each of sail.py's CPU kernels (--kernels torch, onednn) and the one `auto` picks;
  3. end-to-end on the real env, for each --threads: env steps/s after the warm-up of the plain
     loop, of sail.py's defaults and of the paper's SAIL (`sail.py --algo sail-paper`), both
     sail.py runs timed by their own progress.csv (evaluations excluded); with --breakdown also
     the defaults with each addition that costs compute turned off; then two runs of the defaults
     side by side with one thread each, as grids run them on a 2-core machine;
  4. peak memory: a Walker2d run's state with a full 1M-transition self buffer, and the time to
     write its checkpoint (sail.py writes one at every evaluation).
The plain loop is CleanRL's td3_continuous_action.py reduced to its update: two nn.Linear
critics, one update per env step, a Python loop for Polyak averaging, numpy replay storage
copied to torch for every batch.
"""

import copy
import csv
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

import cpu_kernels
import plumbing
import td3
from buffers import ReplayBuffer, TeacherBuffer, mixed_batch
from discriminator import Discriminator, shaped_reward, train_discriminator
from envs import make_env
from plumbing import ArgumentParser, cpu_model, positive_int

HERE = os.path.dirname(os.path.abspath(__file__))
DISC_FREQ, DISC_STEPS, DISC_LR = 500, 10, 1e-3  # sail.py's defaults


def parse_args():
    p = ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Walker2d-v5", help="env of the end-to-end part and the sizes")
    p.add_argument("--threads", type=plumbing.threads, nargs="+", default=[1, 2], help="torch CPU threads, each timed")
    p.add_argument("--hidden", type=positive_int, default=256, help="hidden size of both layers of every network")
    p.add_argument("--batch-size", type=positive_int, default=256, help="batch size")
    p.add_argument("--updates", type=positive_int, default=1000, help="timed updates of part 2, per loop")
    p.add_argument("--env-steps", type=positive_int, default=2000, help="timed env steps of part 3, per loop")
    p.add_argument("--warmup", type=positive_int, default=1000, help="random env steps before the timed ones")
    p.add_argument("--breakdown", action="store_true", help="part 3 also times the defaults without each addition")
    p.add_argument("--skip-memory", action="store_true", help="skip part 4")
    args = p.parse_args()
    return args


# ---------------------------------------------------------------------------------------------
# The plain reference: CleanRL's TD3 update
# ---------------------------------------------------------------------------------------------

class QNetwork(nn.Module):
    def __init__(self, obs_dim, act_dim, hidden):
        super().__init__()
        self.fc1, self.fc2, self.fc3 = nn.Linear(obs_dim + act_dim, hidden), nn.Linear(hidden, hidden), nn.Linear(hidden, 1)

    def forward(self, x, a):
        x = torch.cat([x, a], 1)
        return self.fc3(F.relu(self.fc2(F.relu(self.fc1(x)))))


class PlainActor(nn.Module):
    def __init__(self, obs_dim, act_dim, hidden):
        super().__init__()
        self.fc1, self.fc2, self.fc_mu = nn.Linear(obs_dim, hidden), nn.Linear(hidden, hidden), nn.Linear(hidden, act_dim)

    def forward(self, x):
        return torch.tanh(self.fc_mu(F.relu(self.fc2(F.relu(self.fc1(x))))))


class PlainTD3:
    """CleanRL's update, hyperparameters as TD3's defaults; actions in [-1, 1]."""

    def __init__(self, obs_dim, act_dim, hidden, capacity):
        self.actor, self.qf1, self.qf2 = PlainActor(obs_dim, act_dim, hidden), *(QNetwork(obs_dim, act_dim, hidden) for _ in range(2))
        self.target_actor, self.qf1_target, self.qf2_target = map(copy.deepcopy, (self.actor, self.qf1, self.qf2))
        self.q_optimizer = torch.optim.Adam(list(self.qf1.parameters()) + list(self.qf2.parameters()), lr=3e-4)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.storage = {k: np.zeros((capacity, d), np.float32) for k, d in
                        (("obs", obs_dim), ("actions", act_dim), ("rewards", 1), ("next_obs", obs_dim), ("dones", 1))}
        self.size, self.step = 0, 0

    def add(self, obs, action, reward, next_obs, done):
        for k, v in zip(self.storage, (obs, action, reward, next_obs, done)):
            self.storage[k][self.size % len(self.storage[k])] = v
        self.size += 1

    def act(self, obs):
        with torch.no_grad():
            action = self.actor(torch.Tensor(obs).unsqueeze(0))[0]
            action += torch.normal(0, torch.full_like(action, 0.1))
        return action.numpy().clip(-1, 1)

    def update(self, batch_size):
        self.step += 1
        idx = np.random.randint(0, min(self.size, len(self.storage["obs"])), size=batch_size)
        obs, actions, rewards, next_obs, dones = (torch.tensor(v[idx]) for v in self.storage.values())
        with torch.no_grad():
            clipped_noise = (torch.randn_like(actions) * 0.2).clamp(-0.5, 0.5)
            next_actions = (self.target_actor(next_obs) + clipped_noise).clamp(-1, 1)
            min_q = torch.min(self.qf1_target(next_obs, next_actions), self.qf2_target(next_obs, next_actions))
            next_q_value = rewards.flatten() + (1 - dones.flatten()) * 0.99 * min_q.view(-1)
        qf_loss = (F.mse_loss(self.qf1(obs, actions).view(-1), next_q_value)
                   + F.mse_loss(self.qf2(obs, actions).view(-1), next_q_value))
        self.q_optimizer.zero_grad()
        qf_loss.backward()
        self.q_optimizer.step()
        if self.step % 2 == 0:
            actor_loss = -self.qf1(obs, self.actor(obs)).mean()
            self.actor_optimizer.zero_grad()
            actor_loss.backward()
            self.actor_optimizer.step()
            for net, target in ((self.actor, self.target_actor), (self.qf1, self.qf1_target), (self.qf2, self.qf2_target)):
                for param, target_param in zip(net.parameters(), target.parameters()):
                    target_param.data.copy_(0.005 * param.data + 0.995 * target_param.data)


# ---------------------------------------------------------------------------------------------
# Measurements
# ---------------------------------------------------------------------------------------------

def per_second(fn, n, repeats=3):
    """Best rate of `repeats` timings of n calls (the least disturbed by other processes)."""
    best = 0.0
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(n):
            fn()
        best = max(best, n / (time.perf_counter() - start))
    return best


def matmul_gflops(size=256):
    a, b = torch.randn(size, size), torch.randn(size, size)
    out = torch.empty(size, size)
    flops = 2 * size**3
    mkl = per_second(lambda: torch.mm(a, b, out=out), 2000) * flops / 1e9
    onednn = per_second(lambda: cpu_kernels.linear(a, b), 2000) * flops / 1e9
    return mkl, onednn


def update_flops(obs_dim, act_dim, hidden, batch_size, discriminator=True, policy_delay=2):
    """Matmul FLOPs of one TD3 update (with SAIL's reward: `discriminator`); a backward pass
    costs twice its forward pass."""
    mlp = lambda sizes: 2 * sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))  # noqa: E731
    critic = mlp([obs_dim + act_dim, hidden, hidden, 1])
    actor = mlp([obs_dim, hidden, hidden, act_dim])
    target = actor + 2 * critic                     # y = r + gamma min_i Q'_i(s', pi'(s') + noise)
    critic_step = 3 * 2 * critic                    # both critics, forward and backward
    reward = critic if discriminator else 0         # D(s, a), the critic's sizes
    actor_step = (3 * actor + 2 * critic) / policy_delay  # Q1 backward to its input only
    return batch_size * (target + critic_step + reward + actor_step)


def sail_flags(args, threads, output_dir):
    """sail.py's command line at the bench's sizes (its defaults otherwise): --warmup random steps, then
    --env-steps timed ones; a CSV row (and an evaluation of one episode) at the end of each, and between."""
    return ["--env", args.env, "--threads", str(threads), "--hidden", str(args.hidden), str(args.hidden),
            "--disc-hidden", str(args.hidden), str(args.hidden), "--batch-size", str(args.batch_size),
            "--learning-starts", str(args.warmup), "--total-timesteps", str(args.warmup + args.env_steps),
            "--eval-freq", str(math.gcd(args.warmup, args.env_steps)), "--eval-episodes", "1", "--output-dir", output_dir]


def paper_sail_update(agent, disc, teacher_buffer, self_buffer, batch_size):
    """The paper's SAIL update as sail.py runs it: a batch of 0.5 R_E + 0.5 R_B, rewarded by -log(1 - D)."""
    (obs, actions, next_obs, terminated), _, _ = mixed_batch(teacher_buffer, self_buffer, batch_size, 0.5)
    agent.update(obs, actions, shaped_reward(disc, obs, actions, "sail"), next_obs, terminated)


def updates_on_random_data(args, obs_dim, act_dim):
    """Part 2: updates/s of both on the same random transitions (one teacher episode, 1e5 own),
    SAIL with each kind of CPU kernels; returns plain's rate, SAIL's rates and auto's choice."""
    rng = np.random.default_rng(0)
    n = 100_000
    data = [rng.standard_normal((n, obs_dim)).astype(np.float32), rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
            np.zeros(n, np.float32), rng.standard_normal((n, obs_dim)).astype(np.float32), np.zeros(n, np.float32)]
    plain = PlainTD3(obs_dim, act_dim, args.hidden, n)
    for k, v in zip(plain.storage, data):
        plain.storage[k][:] = v.reshape(n, -1)
    plain.size = n

    self_buffer = ReplayBuffer(obs_dim, act_dim, n)
    for t, v in zip(self_buffer.tensors(), data):
        t.copy_(torch.from_numpy(v))
    self_buffer.size = n
    self_buffer.episode_returns[:n] = torch.randn(n // 1000).repeat_interleave(1000)  # for the return bonus
    teacher_buffer = TeacherBuffer(10_000)
    teacher_buffer.add_episode(0.0, *(torch.from_numpy(data[i][:1000]) for i in (0, 1, 3, 4)))

    def sail_update_fn(kernels):
        agent = td3.TD3(obs_dim, act_dim, -np.ones(act_dim), np.ones(act_dim), hidden=[args.hidden] * 2)
        disc = Discriminator(obs_dim, act_dim, [args.hidden] * 2)
        disc_optimizer = td3.make_adam(disc.parameters(), DISC_LR)
        cpu_kernels.apply(kernels, [*agent.networks(), disc])

        def update():
            if agent.num_updates % DISC_FREQ == 0:  # D is trained every --disc-freq env steps
                train_discriminator(disc, disc_optimizer, teacher_buffer, self_buffer, DISC_STEPS, args.batch_size,
                                    0.01, 10.0)
            paper_sail_update(agent, disc, teacher_buffer, self_buffer, args.batch_size)
        return agent, disc, update

    kinds = ["torch", "onednn"] if cpu_kernels.AVAILABLE else ["torch"]
    fns = {"plain": lambda: plain.update(args.batch_size)}
    for kind in kinds:
        agent, disc, fns[kind] = sail_update_fn(kind)
    agent, disc, _ = sail_update_fn("torch")
    auto = cpu_kernels.choose("auto", [agent.actor.net, agent.critic.q1.net, disc.net], args.batch_size, "cpu")
    for fn in fns.values():  # warm all up
        for _ in range(50):
            fn()
    rates = {name: [] for name in fns}
    for _ in range(3):  # interleaved, so that a disturbance hits all
        for name, fn in fns.items():
            rates[name].append(per_second(fn, args.updates // 3, 1))
    return max(rates.pop("plain")), {k: max(v) for k, v in rates.items()}, auto


def plain_loop_env_steps(args):
    """Part 3, plain: CleanRL's loop on the same env (sparse reward, time feature) as SAIL's."""
    env = make_env(args.env, seed=1)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    plain = PlainTD3(obs_dim, act_dim, args.hidden, args.warmup + args.env_steps)
    obs, _ = env.reset()
    start = None
    for step in range(args.warmup + args.env_steps):
        if step == args.warmup:
            start = time.perf_counter()
        action = env.action_space.sample() if step < args.warmup else plain.act(obs)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        plain.add(obs, action, reward, next_obs, terminated)
        obs = next_obs if not (terminated or truncated) else env.reset()[0]
        if step >= args.warmup:
            plain.update(args.batch_size)
    return args.env_steps / (time.perf_counter() - start)


def sail_env_steps(args, threads, *flag_sets):
    """Part 3, SAIL: sail.py itself, once per set of extra flags, all at the same time (each in its own
    process); the env steps/s of each after the warm-up, from its CSV (whose steps_per_second excludes
    the evaluations)."""
    with tempfile.TemporaryDirectory() as tmp:
        procs = [subprocess.Popen([sys.executable, os.path.join(HERE, "sail.py"), *flags, "--run-name", str(i),
                                   *sail_flags(args, threads, tmp)],
                                  cwd=HERE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for i, flags in enumerate(flag_sets)]
        rates = []
        for i, proc in enumerate(procs):
            stderr = proc.communicate()[1]
            if proc.returncode != 0:
                sys.exit(f"bench.py: error: sail.py failed: {(stderr.strip().splitlines() or ['?'])[-1]}")
            with open(os.path.join(tmp, str(i), "progress.csv")) as f:
                rows = list(csv.DictReader(f))
            steps = [int(r["global_step"]) for r in rows]
            seconds = sum((b - a) / float(r["steps_per_second"]) for a, b, r in zip(steps, steps[1:], rows[1:])
                          if a >= args.warmup)
            rates.append(args.env_steps / seconds)
    return rates


# the defaults' additions that cost compute in every update, each turned off (--breakdown)
ADDITIONS_OFF = {"the learned action cost": ["--action-cost", "none"],
                 "the return decomposition": ["--return-decomposition", "0"],
                 "LayerNorm in the critics": ["--no-critic-layer-norm"]}


MEMORY_SCRIPT = """
import resource, tempfile, time, torch, numpy as np
import plumbing, td3
from buffers import ReplayBuffer, TeacherBuffer, mixed_batch
from discriminator import Discriminator, shaped_reward, train_discriminator
from envs import EnvState, make_env
torch.set_num_threads({threads})
# a 1M-step run's state: its buffer full (every page written), networks, D, both envs
env, eval_env = make_env("Walker2d-v5", 1), make_env("Walker2d-v5", 101)
obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
buffer = ReplayBuffer(obs_dim, act_dim, 10**6)
for t in buffer.tensors():
    t.normal_()
buffer.size = 10**6
buffer.episode_returns.copy_(torch.randn(1000).repeat_interleave(1000))
teacher = TeacherBuffer(10_000)
teacher.add_episode(0.0, *(t[:10_000] for t in (buffer.obs, buffer.actions, buffer.next_obs, buffer.terminated)))
agent = td3.TD3(obs_dim, act_dim, env.action_space.low, env.action_space.high)
disc = Discriminator(obs_dim, act_dim, [256, 256])
disc_optimizer = td3.make_adam(disc.parameters(), 1e-3)
train_discriminator(disc, disc_optimizer, teacher, buffer, 10, 256, 0.01, 10.0)
for _ in range(100):
    (obs, actions, next_obs, terminated), _, _ = mixed_batch(teacher, buffer, 256, 0.5)
    agent.update(obs, actions, shaped_reward(disc, obs, actions, "sail"), next_obs, terminated)
run_dir = plumbing.make_run_dir(tempfile.mkdtemp(), "memory", {{}})
state = {{"global_step": 10**6, "rows": [], "train_time": 0.0}}
start = time.perf_counter()
plumbing.save_checkpoint(run_dir + "/checkpoint.pt", {{"agent": agent, "disc": disc,
    "disc_optimizer": disc_optimizer, "self_buffer": buffer, "teacher_buffer": teacher, "env": EnvState(env),
    "eval_env": EnvState(eval_env), "rng": plumbing.RNGs(np.random.default_rng(0))}},
    loop=state, obs=env.reset()[0])
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2)
"""


def peak_memory_gb(args):
    """Part 4 in a fresh process, so that parts 1-3 do not count: peak GB, seconds to write the checkpoint."""
    out = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT.format(threads=args.threads[0])], cwd=HERE,
                         capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"bench.py: error: the memory measurement failed: {out.stderr.strip().splitlines()[-1]}")
    seconds, gb = map(float, out.stdout.split()[-2:])
    return gb, seconds


def main(args):
    torch.manual_seed(0)
    np.random.seed(0)
    env = make_env(args.env, seed=0)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    print(f"bench.py: {args.env} (obs {obs_dim} incl. time feature, act {act_dim}), hidden {args.hidden}-{args.hidden}, "
          f"batch {args.batch_size}, torch {torch.__version__}, {time.strftime('%Y-%m-%d')}")
    print(f"CPU: {cpu_model()}, {os.cpu_count()} cores")
    flops = update_flops(obs_dim, act_dim, args.hidden, args.batch_size)
    for threads in args.threads:
        torch.set_num_threads(threads)
        print(f"{threads} thread(s):")
        mkl, onednn = matmul_gflops(args.hidden)
        print(f"1. {args.hidden}x{args.hidden}x{args.hidden} matmul: torch.mm (MKL) {mkl:.0f} GFLOP/s, oneDNN {onednn:.0f} GFLOP/s; one update of the "
              f"paper's SAIL is {flops / 1e9:.3f} GFLOP -> limit {max(mkl, onednn) * 1e9 / flops:.0f} updates/s")
        plain, fast, auto = updates_on_random_data(args, obs_dim, act_dim)
        print(f"2. updates/s on random data: plain TD3 {plain:.0f}; the paper's SAIL " + ", ".join(
            f"--kernels {k} {v:.0f} ({v / plain:.2f}x)" for k, v in fast.items()) + f"; auto picks {auto}")
        plain_sps = plain_loop_env_steps(args)
        variants = {"SAIL's defaults": [], "the paper's SAIL": ["--algo", "sail-paper"]}
        if args.breakdown:
            variants |= {f"the defaults without {name}": flags for name, flags in ADDITIONS_OFF.items()}
        rates = {name: sail_env_steps(args, threads, flags)[0] for name, flags in variants.items()}
        print(f"3. env steps/s on {args.env} (1 update per step, after {args.warmup} random steps): plain TD3 loop "
              f"{plain_sps:.0f}; " + "; ".join(f"{name} {v:.0f} ({v / plain_sps:.2f}x)" for name, v in rates.items()))
    if (os.cpu_count() or 1) >= 2:
        both = sail_env_steps(args, 1, [], [])
        print(f"3. env steps/s of two runs of SAIL's defaults side by side, 1 thread each: {both[0]:.0f} + {both[1]:.0f}"
              f" = {sum(both):.0f}")
    if not args.skip_memory:
        gb, seconds = peak_memory_gb(args)
        print(f"4. peak memory of a Walker2d-v5 run with a full 1M-transition self buffer, after a checkpoint: "
              f"{gb:.2f} GB; writing that checkpoint took {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(plumbing.run_main("bench.py", main, parse_args()))
