"""Learning curves and a results table from run folders (each with config.json and progress.csv).

    python plot.py                                   # every run under results/runs/, into results/
    python plot.py runs/Hopper-v5__sail__1__*        # these runs, into plots/ (or --output-dir)

For each env: evaluation return against env steps, the mean over seeds of each method as a
line and the range over seeds as a band, the teacher's return as a dashed line; BC (no env
steps) as a dotted line at its final return. A run's method is the "method" of its config.json
(sail.py --method, default the preset's name plus the learner flags given; bc.py and gail.py
write theirs), and the runs of one method are its seeds. Writes <env>.png with the presets and
baselines (SAIL, SAIL-paper, DAC, TD3 (sparse), IRCR, RRD, BC, GAIL, POfD), and <env>-ablations.png
with every other method (the paper's ablations, e.g. "SAIL-paper (--fixed-alpha)", and the learner
variants) beside SAIL and SAIL-paper, where there are any (needs matplotlib: `pip install
matplotlib`; without it only the table is written); runs with N > 1 teacher episodes (--num-demos N)
get their own <env>-Ndemos.png and section; results.md with, per env and method:
seeds, env steps, final return (mean of the last 5 evaluations, for BC its last one; mean +- std
over seeds), the env steps at which the evaluation return first reached the teacher's, the env
steps of the first promotion into the teacher buffer, and the mean evaluation return of the early
phase (evaluations up to --early-steps, averaged over seeds). Above those tables, one table of the
presets and baselines (PRESETS) per env: the seeds' final returns as mean, median, range and a 95%
bootstrap interval of the mean (bootstrap_interval), runs on the seeds that no decision saw
(CONFIRMATION_SEEDS) apart from the others. A DAC run whose config.json names no commit (older
code, CODE_RECORDED_ONLY) is "DAC (code not recorded)", a method of its own.
"""

import csv
import glob
import json
import os
import sys
from collections import defaultdict

import numpy as np

import plumbing
from demos import default_demo_path, read_minari
from plumbing import ArgumentParser, ConfigError, atomic_write, first_line

HERE = os.path.dirname(os.path.abspath(__file__))


def parse_args(argv=None):
    p = ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="*", help="run folders (default: results/runs/*)")
    p.add_argument("--output-dir", help="where the PNGs and results.md go (default: results/ for the committed "
                   "runs, plots/ for run folders given)")
    p.add_argument("--last", type=int, default=5, help="evaluations averaged into the final return")
    p.add_argument("--early-steps", type=int, default=100_000,
                   help="the early phase: the table's last column averages the evaluations up to here")
    p.add_argument("--min-steps", type=int, default=0,
                   help="leave out runs (not BC) with fewer env steps, e.g. those still running")
    args = p.parse_args(argv)
    # the committed figures and table are rewritten only from the committed runs
    args.output_dir = args.output_dir or ("plots" if args.runs else os.path.join(HERE, "results"))
    args.runs = args.runs or sorted(glob.glob(os.path.join(HERE, "results", "runs", "*")))
    if not args.runs:
        p.error("no run folders given and none under results/runs/")
    for run in args.runs:
        if not (os.path.isfile(os.path.join(run, "config.json")) and os.path.isfile(os.path.join(run, "progress.csv"))):
            p.error(f"{run} is not a run folder (no config.json and progress.csv)")
    if args.last <= 0 or args.early_steps <= 0:
        p.error("--last and --early-steps must be positive")
    if os.path.exists(args.output_dir) and not os.path.isdir(args.output_dir):
        p.error(f"--output-dir {args.output_dir} is a file")
    return args


# <env>.png: the presets of sail.py and the baselines of bc.py and gail.py, under the names the scripts give
# them; every other method (a preset with flags set, in parentheses) goes to <env>-ablations.png beside SAIL
# and SAIL-paper
PRESETS = ("SAIL", "SAIL-paper", "DAC", "TD3 (sparse)", "IRCR", "RRD", "BC", "GAIL", "POfD")
PAPER_SAIL = "SAIL-paper"  # drawn in both figures, as SAIL is
# seeds that no decision saw (results/grid.py's `confirm`): the first table reports a preset's runs on them apart
# from its runs on the seeds that its choice was made on
CONFIRMATION_SEEDS = (6, 7, 8)
# presets whose committed seeds mix code before and after a fix (DAC: the zero action in its absorbing state) and
# whose older runs name no commit in config.json: such a run is drawn and tabled as "<method> (code not recorded)",
# apart from the preset, so that what compares SAIL with the preset counts only runs of code that is known
CODE_RECORDED_ONLY = ("DAC",)


def method_name(config, run_dir="the run"):
    """What a run is: the "method" its config.json records (sail.py --method, bc.py, gail.py). Runs of
    one method and env are the seeds of one line."""
    method = config.get("method")
    if not isinstance(method, str) or not method:
        raise ConfigError(f"{run_dir}/config.json names no method (a run of older code: see "
                          "results/archive/README.md)")
    return method


def teacher_return(config):
    """Mean return of the teacher episodes the run used (the first --num-demos of its file)."""
    path = config.get("demos") or default_demo_path(config["env"])
    try:
        if os.path.isfile(path):
            with np.load(path, allow_pickle=False) as demos:
                returns = demos["episode_returns"]
        else:  # a Minari dataset, its folder or its id in the local store
            returns = read_minari(path)["episode_returns"]
        return float(np.mean(returns[:config["num_demos"]]))
    except ConfigError:
        raise
    except Exception as e:
        raise ConfigError(f"cannot read the teacher's returns from {path}: {first_line(e)}") from None


def load_run(run_dir):
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            config = json.load(f)
        with open(os.path.join(run_dir, "progress.csv")) as f:
            rows = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]
    except Exception as e:
        raise ConfigError(f"cannot read the run {run_dir}: {first_line(e)}") from None
    if not isinstance(config, dict) or not {"env", "algo"} <= set(config):
        raise ConfigError(f"{run_dir}/config.json is not a run's config (no env and algo)")
    return config, rows


BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED = 10_000, 0


def bootstrap_interval(values, level=0.95, resamples=BOOTSTRAP_RESAMPLES, seed=BOOTSTRAP_SEED):
    """Percentile bootstrap interval of the mean of values (one final return per seed): draw `resamples`
    samples of as many values with replacement (numpy, a fixed seed: the same values give the same
    interval), take each one's mean, and return the central `level` of those means. With two or three
    values it is their range (a resample of the lowest value alone is 1 in 4 or 1 in 27, more than 2.5%);
    with one there is none (NaNs)."""
    values = np.asarray(values, dtype=float)
    if len(values) < 2:
        return float("nan"), float("nan")
    means = values[np.random.default_rng(seed).integers(len(values), size=(resamples, len(values)))].mean(1)
    low, high = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def final_returns(runs, last):
    """Each seed's final return: the mean of its last `last` evaluations."""
    return [float(np.mean([r["eval_return"] for r in rows[-last:]])) for _, rows in runs]


def seed_statistics(finals, teacher):
    """The headline table's cells for one method's final returns."""
    low, high = bootstrap_interval(finals)
    return {"seeds": len(finals), "mean": f"{np.mean(finals):.0f}", "median": f"{np.median(finals):.0f}",
            "min to max": f"{min(finals):.0f}" if len(finals) == 1 else f"{min(finals):.0f} to {max(finals):.0f}",
            "95% interval of the mean": "" if np.isnan(low) else f"{low:.0f} to {high:.0f}",
            "vs teacher": f"{np.mean(finals) / teacher:.2f}x"}


def seed_groups(method, runs, seeds):
    """A method's runs for the first table: those on CONFIRMATION_SEEDS apart from the others, each group
    named by its seeds ("SAIL, seeds 6, 7, 8"); all together under the method's name where it has none."""
    fresh = [run for run in runs if seeds[run[0]] in CONFIRMATION_SEEDS]
    if not fresh:
        return {method: runs}
    groups = ([run for run in runs if seeds[run[0]] not in CONFIRMATION_SEEDS], fresh)
    return {f"{method}, seeds {', '.join(str(s) for s in sorted(seeds[run[0]] for run in group))}": group
            for group in groups if group}


def summarise(runs, teacher, last, early_steps):
    """One table row for the runs (seeds) of one method."""
    finals = final_returns(runs, last)
    early = [np.mean([r["eval_return"] for r in rows if r["global_step"] <= early_steps]) for _, rows in runs]
    reached, promoted = [], []
    for _, rows in runs:
        reached.append(next((r["global_step"] for r in rows if r["eval_return"] >= teacher), None))
        promoted.append(next((r["global_step"] for r in rows if r["promotions"] > 0), None))
    steps = [rows[-1]["global_step"] for _, rows in runs]

    def when(values):
        return ", ".join("never" if v is None else f"{v / 1000:.0f}k" for v in values)

    return {"seeds": len(runs), "env steps": when(steps), "final": f"{np.mean(finals):.0f} +- {np.std(finals):.0f}",
            "per seed": ", ".join(f"{v:.0f}" for v in finals),
            "vs teacher": f"{np.mean(finals) / teacher:.2f}x",
            "reached teacher": when(reached), "first promotion": when(promoted), "early": f"{np.mean(early):.0f}"}


def plot_env(env_id, num_demos, methods, teacher, path, colors):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for method, runs in sorted(methods.items()):
        color = colors[method]
        if method == "BC":
            final = np.mean([rows[-1]["eval_return"] for _, rows in runs])
            ax.axhline(final, color=color, linestyle=":", label=f"BC ({len(runs)} seed{'s' * (len(runs) > 1)}, final)")
            continue
        steps = sorted({r["global_step"] for _, rows in runs for r in rows})
        returns = np.full((len(runs), len(steps)), np.nan)  # NaN where a seed has not got yet
        for i, (_, rows) in enumerate(runs):
            for r in rows:
                returns[i, steps.index(r["global_step"])] = r["eval_return"]
        ax.plot(steps, np.nanmean(returns, 0), color=color, label=f"{method} ({len(runs)} seed{'s' * (len(runs) > 1)})")
        ax.fill_between(steps, np.nanmin(returns, 0), np.nanmax(returns, 0), color=color, alpha=0.2)
    ax.axhline(teacher, color="k", linestyle="--", label=f"teacher ({teacher:.0f})")
    episodes = "1 teacher episode" if num_demos == 1 else f"{num_demos} teacher episodes"
    ax.set(title=f"{env_id}, sparse episodic reward, {episodes}", xlabel="env steps",
           ylabel="evaluation return (dense, deterministic policy)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    os.replace(tmp, path)
    plt.close(fig)


def write_results(args):
    by_env = defaultdict(lambda: defaultdict(list))
    teachers, seeds = {}, {}
    left_out = []
    for run in args.runs:
        config, rows = load_run(run)
        if not rows or (config["algo"] != "bc" and rows[-1]["global_step"] < args.min_steps):
            left_out.append(f"{os.path.basename(os.path.normpath(run))} ({rows[-1]['global_step'] / 1000:.0f}k steps)"
                            if rows else os.path.basename(os.path.normpath(run)))
            continue
        key = (config["env"], config.get("num_demos", 1))  # 1 and 4 teacher episodes: apart
        method = method_name(config, run)
        if method in CODE_RECORDED_ONLY and not config.get("commit"):
            method += " (code not recorded)"
        by_env[key][method].append((run, rows))
        seeds[run] = config.get("seed")
        if config["algo"] not in ("td3", "ircr"):  # no teacher episodes used
            teachers[key] = teacher_return(config)
    os.makedirs(args.output_dir, exist_ok=True)

    # the presets and baselines first: the spread of their seeds' final returns
    headline = ["env", "method", "seeds", "mean", "median", "min to max", "95% interval of the mean", "vs teacher"]
    lines = []
    for (env_id, num_demos), methods in sorted(by_env.items()):
        title = env_id if num_demos == 1 else f"{env_id}, {num_demos} teacher episodes"
        for method in (m for m in PRESETS if m in methods):
            for name, runs in seed_groups(method, methods[method], seeds).items():
                finals = final_returns(runs, 1 if method == "BC" else args.last)
                row = seed_statistics(finals, teachers.get((env_id, num_demos), float("nan")))
                lines.append("| " + " | ".join(str((row | {"env": title, "method": name})[c]) for c in headline) + " |")
    if lines:
        lines = ["### Final returns of the presets and baselines", "",
                 f"Per seed the mean of its last {args.last} evaluations (BC: its last); over the seeds their mean, "
                 f"median and range, and a 95% percentile bootstrap interval of the mean ({BOOTSTRAP_RESAMPLES:,} "
                 f"resamples of the seeds with replacement, numpy seed {BOOTSTRAP_SEED}: `plot.bootstrap_interval`; "
                 "with two or three seeds it is their range, and with so few seeds it understates the "
                 "uncertainty).", "", "| " + " | ".join(headline) + " |", "|" + "---|" * len(headline), *lines, ""]

    columns = ["method", "seeds", "env steps", "final", "per seed", "vs teacher", "reached teacher", "first promotion",
               "early"]
    for (env_id, num_demos), methods in sorted(by_env.items()):
        teacher = teachers.get((env_id, num_demos), float("nan"))
        header = columns[:-1] + [f"mean to {args.early_steps / 1000:.0f}k"]
        title = env_id if num_demos == 1 else f"{env_id}, {num_demos} teacher episodes"
        name = env_id if num_demos == 1 else f"{env_id}-{num_demos}demos"
        lines += [f"### {title} (teacher {teacher:.0f})", "", "| " + " | ".join(header) + " |",
                  "|" + "---|" * len(columns)]
        for method, runs in sorted(methods.items()):
            row = summarise(runs, teacher, 1 if method == "BC" else args.last, args.early_steps) | {"method": method}
            if method == "BC":
                row |= {"env steps": "0", "reached teacher": "", "first promotion": "", "early": ""}
            lines.append("| " + " | ".join(str(row[c]) for c in columns) + " |")
        lines.append("")
        # the presets and baselines in one figure; the paper's ablations and the variants beside SAIL and SAIL-paper
        baselines = {m: runs for m, runs in methods.items() if m in PRESETS}
        ablations = {m: runs for m, runs in methods.items() if m not in PRESETS or m in ("SAIL", PAPER_SAIL)}
        colors = {"SAIL": "C0", PAPER_SAIL: "C1"}  # the two drawn in both figures keep their colours; the
        for figure in (baselines, ablations):   # others take the next ones, so no two lines of a figure share one
            colors |= {m: f"C{i}" for i, m in enumerate(sorted(set(figure) - set(colors)), start=2)}
        try:
            if baselines:
                plot_env(env_id, num_demos, baselines, teacher, os.path.join(args.output_dir, f"{name}.png"), colors)
            if set(ablations) - set(baselines):
                plot_env(env_id, num_demos, ablations, teacher, os.path.join(args.output_dir, f"{name}-ablations.png"),
                         colors)
        except ImportError:
            print("plot.py: matplotlib is not installed (pip install matplotlib): writing the table only",
                  file=sys.stderr)
    if left_out:
        lines.append(f"Left out (fewer than {args.min_steps} env steps): {', '.join(left_out)}.")
    path = os.path.join(args.output_dir, "results.md")
    atomic_write(path, lambda f: f.write("\n".join(lines).encode()))
    print("\n".join(lines))
    print(f"\nwrote {path} and the figures beside it", file=sys.stderr)
    return 0


def main(argv=None):
    return plumbing.run_main("plot.py", write_results, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
