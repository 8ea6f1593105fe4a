"""Would `--teacher-keep pareto` and `--teacher-keep return` have kept the same R_E in this run?

    python results/keep_replay.py RUN_DIR

RUN_DIR is a sail.py run folder (config.json and checkpoint.pt) whose self buffer R_B still holds
every episode of the run (fewer env steps than --buffer-size). The two rules differ only in which
episode leaves a full R_E (buffers.TeacherBuffer), and a run is otherwise deterministic, so the
same run with the other rule is the same run, step for step, until the first finished episode after
which the two R_E differ. This replays both rules on the run's own finished episodes, in order,
starting from its teacher episodes (the demo file's first --num-demos), and prints the step at which
the two part, or that they never do: then the run with the other rule on the same seed is this run.
It also checks the replay against the R_E that the checkpoint holds (R_B keeps each episode's
return in float32, R_E in float64: a promotion that hinged on a difference below float32's
precision would show up as a mismatch there).
"""

import argparse
import os
import sys

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from buffers import TeacherBuffer  # noqa: E402
from demos import default_demo_path, load_demos  # noqa: E402
from plumbing import run_folder_checkpoint, run_folder_config  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("run_dir")
args = p.parse_args()
config = run_folder_config(p, args.run_dir)
state = run_folder_checkpoint(p, args.run_dir)
self_buffer = state["self_buffer"]
if self_buffer["ptr"] != self_buffer["size"]:
    p.error(f"{args.run_dir}: R_B has wrapped around, its first episodes are gone")
if config.get("no_adaptation") or config.get("reward") not in ("sail", "airl"):
    p.error(f"{args.run_dir}: a run whose R_E is never updated")

# the finished episodes in the order they ended: (return, length, first step)
returns, lengths = self_buffer["episode_returns"], self_buffer["episode_lengths"]
episodes, start = [], 0
while start < self_buffer["size"] and not torch.isnan(returns[start]):
    episodes.append((float(returns[start]), int(lengths[start]), start))
    start += int(lengths[start])

env = gym.make(config["env"])
teacher = [(float(ep["episodic_return"]), len(ep["actions"])) for ep in load_demos(
    config["demos"] or default_demo_path(config["env"]), config["env"], env.observation_space.shape[0],
    env.action_space.shape[0], config["num_demos"])]


def placeholder(length):  # the rules read only the return and the length of an episode
    return torch.zeros(length, 1), torch.zeros(length, 1), torch.zeros(length, 1), torch.zeros(length)


def kept(buffer):
    return [(ret, len(data[0])) for ret, data in buffer.episodes]


rules = {keep: TeacherBuffer(config["teacher_capacity"], keep) for keep in ("return", "pareto")}
for buffer in rules.values():
    for ret, length in teacher:
        buffer.add_episode(ret, *placeholder(length))
promotions, parted_at = 0, None
for ret, length, first in episodes:
    promotions += rules[config["teacher_keep"]].promote(ret, *placeholder(length))
    other = rules["pareto" if config["teacher_keep"] == "return" else "return"]
    other.promote(ret, *placeholder(length))
    if parted_at is None and kept(rules["return"]) != kept(rules["pareto"]):
        parted_at = first + length

own = kept(rules[config["teacher_keep"]])
saved = [(ret, len(data[0])) for ret, data in state["teacher_buffer"]["episodes"]]
matches = len(own) == len(saved) and np.allclose([r for r, _ in own], [r for r, _ in saved], rtol=1e-6) and \
    [n for _, n in own] == [n for _, n in saved]
print(f"{config['env']}, --teacher-keep {config['teacher_keep']}, seed {config['seed']}: {len(episodes)} finished "
      f"episodes to step {start}, teacher {', '.join(f'{r:.0f} ({n} steps)' for r, n in teacher)}")
print(f"replayed with its own rule: {promotions} promotions, R_E at the end "
      f"{'matches' if matches else 'DOES NOT match'} the checkpoint's ({len(saved)} episodes)")
print("the two rules never part: the other rule's run on this seed is this run" if parted_at is None else
      f"the two rules part after the episode that ends at step {parted_at}")
sys.exit(0 if matches else 1)
