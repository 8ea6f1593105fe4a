"""What every training script here needs around its loop, in one place.

sail.py, bc.py, gail.py and make_demos.py use it for: one-line errors on bad input, a run folder
with its config.json, the progress CSV, atomic writes, checkpoints (a dict of state_dicts, loaded
with torch's weights-only unpickler), model.pt, --resume, and a clean stop on Ctrl-C or SIGTERM.
None of it is reinforcement learning; it is here so that the scripts can be about that.
"""

import argparse
import csv
import fcntl
import io
import json
import math
import os
import platform
import shlex
import signal
import subprocess
import sys
import time

# progress.csv's columns, one row per evaluation, the same for every script so that plot.py reads them all
PROGRESS_COLUMNS = ["global_step", "eval_return", "eval_return_std", "eval_length", "train_episodic_return",
                    "teacher_threshold", "teacher_episodes", "promotions", "alpha", "disc_loss", "disc_teacher",
                    "disc_self", "reward_mean", "decomposition_loss", "decomposition_action_cost", "critic_loss",
                    "actor_loss", "q", "updates", "steps_per_second", "time"]

# torch and numpy are imported inside the functions that use them: a script which only needs the flags
# and files here (results/grid.py) starts without loading torch (~2 s), and a script's quiet Ctrl-C handler
# (quiet_interrupt_while_importing) is in place before numpy loads (~0.1 s)


class ConfigError(Exception):
    """Bad user input (env id, demo file, flag value, run folder): printed as one line."""


def first_line(error):
    """An exception as one line of text, for one-line error messages."""
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


class ArgumentParser(argparse.ArgumentParser):
    """argparse that shows each flag's default in --help and reports a bad flag as one line (no usage
    block) with exit code 2."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, formatter_class=argparse.ArgumentDefaultsHelpFormatter, **kwargs)

    def error(self, message):
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(2)

    def given_flags(self, argv):
        """The names of the flags written on the command line, whatever their values.

        Parsing into a namespace that already holds every name stops argparse from filling in
        defaults, so a flag given with its default value still counts as given.
        """
        unset = object()
        namespace = argparse.Namespace(**{name: unset for name in vars(self.parse_args([]))})
        self.parse_known_args(argv, namespace=namespace)
        return {name for name, value in vars(namespace).items() if value is not unset}


def as_flag(name, value):
    """A flag and its value as written on a command line: "--gamma 0.995", "--no-time-feature"."""
    flag = "--" + name.replace("_", "-")
    if isinstance(value, bool):
        return flag if value else "--no-" + flag[2:]
    return f"{flag} {' '.join(map(str, value)) if isinstance(value, (list, tuple)) else value}"


def count(n, noun):
    """ "1 episode", "4 episodes"."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def positive_int(text):
    """argparse type: an integer > 0 (bad values become argparse's one-line error)."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def seed(text):
    """argparse type: a seed that numpy, gymnasium and torch all accept (0 <= seed < 2**32)."""
    value = int(text)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**32), got {value}")
    return value


def non_negative_float(text):
    """argparse type: a finite number >= 0 (nan and inf are refused: a learning rate of inf would
    only show up later as a diverged loss)."""
    value = float(text)
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def positive_float(text):
    """argparse type: a finite number > 0 (a learning rate of 0 trains nothing)."""
    value = non_negative_float(text)
    if value == 0:
        raise argparse.ArgumentTypeError("must be > 0, got 0")
    return value


def unit_interval(text):
    """argparse type: a number in (0, 1], as a discount or a Polyak rate."""
    value = float(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text}")
    return value


def threads(text):
    """argparse type: torch's CPU threads, 1 to 4x the CPUs here (far more makes the thread pools fail
    to start, a crash rather than an error)."""
    value = positive_int(text)
    most = 4 * (os.cpu_count() or 1)
    if value > most:
        raise argparse.ArgumentTypeError(f"must be at most {most} (4x the {os.cpu_count()} CPUs here), got {value}")
    return value


def quiet_interrupt_while_importing(prog):
    """Ctrl-C while a script imports torch: one line and exit 130, no traceback. os._exit, since an
    exception raised in Python code that torch's C++ import calls aborts the process."""
    signal.signal(signal.SIGINT, lambda signum, frame: os._exit(print(f"{prog}: interrupted", file=sys.stderr,
                                                                      flush=True) or 130))


def run_main(prog, main, argv=None):
    """Calls main(argv) and turns the ways a run can stop into exit codes, never a traceback:
    bad input is one line and exit 1, Ctrl-C outside the training loop exit 130, and a reader
    that closed stdout early (`| head`) exit 1, quietly."""
    # from here Ctrl-C is a KeyboardInterrupt, not the scripts' import-time os._exit, so that the
    # finally blocks and atomic writes of main still run
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = main(argv)
        sys.stdout.flush()  # here, so that a reader gone early is caught below, not at exit
        return code
    except ConfigError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout to /dev/null, so that the exit's own flush cannot fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


# ---------------------------------------------------------------------------------------------
# Files: atomic writes, the run folder, the CSV
# ---------------------------------------------------------------------------------------------

def atomic_write(path, write):
    """Calls write(file) on a temp file beside `path`, then renames it to `path`: an interrupted
    write never leaves a broken file behind."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:  # a full disk: OSError, or a RuntimeError from torch's zip writer
        kept = f"; the previous {os.path.basename(path)} is kept" if os.path.exists(path) else ""
        raise ConfigError(f"cannot write {path}: {first_line(e)}{kept}") from None
    finally:
        if os.path.exists(tmp):  # the write failed: leave no temp file behind
            os.remove(tmp)


def check_writable(path):
    """ConfigError unless a file can be created at `path` (checked before any training)."""
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise ConfigError(f"cannot write {path}: it is a folder")
    try:
        os.makedirs(folder, exist_ok=True)
        probe = os.path.join(folder, f".write-test{os.getpid()}")
        open(probe, "w").close()
        os.remove(probe)
    except OSError as e:
        raise ConfigError(f"cannot write {path}: {e.strerror}") from None


def cpu_model():
    """The CPU as the kernel reports it: model name, family/model numbers and AVX-512 (a VM may
    show only "AMD EPYC"; the numbers tell its generations apart). Speed means little without it."""
    try:
        with open("/proc/cpuinfo") as f:
            info = dict(line.split(":", 1) for line in f.read().split("\n\n")[0].splitlines() if ":" in line)
        info = {k.strip(): v.strip() for k, v in info.items()}
        avx512 = "AVX-512" if "avx512f" in info.get("flags", "").split() else "no AVX-512"
        return f"{info['model name']} (family {info['cpu family']}, model {info['model']}, {avx512})"
    except (OSError, KeyError):
        return platform.processor() or platform.machine()


def git_commit():
    """The commit of the code that runs (`-dirty` if it has uncommitted changes), None outside a git checkout."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=12"], cwd=here,
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = out.stdout.strip()
    return commit if out.returncode == 0 and commit else None


def make_run_dir(output_dir, name, config):
    """Creates output_dir/name with config.json: what the run is (its method, every flag), the code
    that ran it (commit), the command and the CPU, which the run's steps_per_second means little
    without. Nothing of where it ran: no folder of this machine is written."""
    if not name or name in (".", "..") or os.sep in name or (os.altsep and os.altsep in name):
        raise ConfigError(f"--run-name {name!r}: a run name is a folder name, not a path")
    run_dir = os.path.join(output_dir, name)
    if os.path.exists(run_dir):
        raise ConfigError(f"run folder {run_dir} already exists (use --resume {run_dir} to continue it)")
    check_writable(os.path.join(run_dir, "config.json"))
    config = {k: v for k, v in config.items() if k not in ("output_dir", "resume", "given")}
    command = shlex.join(["python", os.path.basename(sys.argv[0]), *sys.argv[1:]])
    commit = git_commit()
    config |= {"command": command, "cpu": cpu_model()} | ({"commit": commit} if commit else {})
    atomic_write(os.path.join(run_dir, "config.json"), lambda f: f.write(json.dumps(config, indent=2).encode()))
    lock_run_dir(run_dir)
    return run_dir


_locks = {}  # run folder -> its open lock file: the lock lasts as long as the process


def lock_run_dir(run_dir):
    """Takes the run folder for this process (an OS lock that ends with the process, so a killed run
    leaves no stale lock): a second process resuming the same run would overwrite its newer checkpoint."""
    key = os.path.realpath(run_dir)
    if key in _locks:  # this process holds it already (a run resumed in the same process)
        return
    f = open(os.path.join(run_dir, ".lock"), "a")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise ConfigError(f"{run_dir} is in use by another process (a run or --resume of it)") from None
    _locks[key] = f


def run_name(env_id, method, seed):
    return f"{env_id}__{method}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}"


def rounded(row):
    """A CSV row with its floats, numpy's too, rounded to 4 decimals."""
    import numpy as np
    return {k: round(float(v), 4) if isinstance(v, (float, np.floating)) else v for k, v in row.items()}


def write_csv(path, columns, rows):
    """Writes all rows (dicts) to `path` atomically; floats rounded to 4 decimals."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows([rounded(row) for row in rows])
    atomic_write(path, lambda f: f.write(text.getvalue().encode()))


class ProgressLog:
    """progress.csv, one row per evaluation (all rows rewritten atomically each time), and with
    `tensorboard` the same numbers as TensorBoard scalars in the run folder.

    `rows` is the loop state's own list, so that a checkpoint holds every row written so far.
    """

    def __init__(self, run_dir, columns, rows, tensorboard=False):
        self.path, self.columns, self.rows = os.path.join(run_dir, "progress.csv"), columns, rows
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter  # checked by check_tensorboard before
            self.writer = SummaryWriter(run_dir)

    def append(self, row):
        row = rounded(row)
        self.rows.append(row)
        write_csv(self.path, self.columns, self.rows)
        if self.writer is not None:
            step = row["global_step"] or row["updates"]  # BC takes no env steps: its gradient steps
            for name, value in row.items():
                if name != "global_step" and isinstance(value, (int, float)) and math.isfinite(value):
                    self.writer.add_scalar(f"progress/{name}", value, step)
            self.writer.flush()


def progress_bar(total, initial, desc, warm_up=0, last_row=None):
    """The training loop's tqdm bar from step `initial`, with the numbers of progress.csv's last row
    (show_row). No time left is shown during the first `warm_up` steps: random steps run ten times as
    fast as learning ones, and an estimate from them would promise minutes for hours."""
    from tqdm import tqdm

    class Bar(tqdm):
        @property
        def format_dict(self):
            d = super().format_dict
            if self.n < warm_up:
                d["bar_format"] = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, warm-up{postfix}]"
            return d
    bar = Bar(total=total, initial=initial, desc=desc, unit="step", dynamic_ncols=True, mininterval=1.0)
    if last_row is not None:  # a resumed run shows where it stood
        show_row(bar, last_row)
    return bar


def show_row(bar, row):
    """The last evaluation's return, the teacher threshold and alpha beside the bar."""
    numbers = {"eval": f"{row['eval_return']:.0f}", "threshold": f"{row['teacher_threshold']:.0f}", "alpha": row["alpha"]}
    bar.set_postfix({k: v for k, v in numbers.items() if v != "nan"}, refresh=False)


def check_tensorboard(parser, args):
    """--tensorboard without the tensorboard package: one line before anything starts."""
    if getattr(args, "tensorboard", False):
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            parser.error("--tensorboard needs the tensorboard package: pip install -r requirements-extras.txt")


# ---------------------------------------------------------------------------------------------
# Checkpoints: plain types and tensors only, so that loading runs no code from the file
# ---------------------------------------------------------------------------------------------

def _to_safe(x):
    """numpy arrays and scalars -> tensors and Python numbers (marked, to be turned back)."""
    import numpy as np
    import torch
    if isinstance(x, np.ndarray):
        return {"__ndarray__": torch.from_numpy(np.ascontiguousarray(x)).clone()}
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {k: _to_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_to_safe(v) for v in x)
    return x


def _from_safe(x):
    if isinstance(x, dict):
        if set(x) == {"__ndarray__"}:
            return x["__ndarray__"].numpy()
        return {k: _from_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_from_safe(v) for v in x)
    return x


def save_checkpoint(path, parts, **values):
    """Writes the state_dict() of every part (networks, optimisers, buffers, envs, RNGs) and
    plain values (tensors, numpy arrays, numbers, strings, lists, dicts) atomically."""
    import torch
    state = {name: part.state_dict() for name, part in parts.items()} | values
    atomic_write(path, lambda f: torch.save(_to_safe(state), f))


def torch_device(name):
    """--device's torch device: auto is CUDA where there is one; cuda without one (a run made on a GPU,
    resumed here, too) is a ConfigError."""
    import torch
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device is available (--device cpu runs on the CPU)")
    return torch.device("cuda" if name != "cpu" and torch.cuda.is_available() else "cpu")


def load_checkpoint(path, parts=(), check=None):
    """Reads a file written by save_checkpoint with torch's weights-only unpickler (a file that
    would run code when unpickled is refused, as is any unreadable one: ConfigError), calls
    `check(state)` if given (it may raise ConfigError before any part is touched), loads the
    state of each of `parts` into it, and returns the whole dict.

    Every tensor is read onto the CPU, where buffers and RNG states live; a part's load_state_dict
    moves its tensors to the part's own device, so a run saved on cuda resumes on cuda or cpu."""
    import torch
    import pickle
    try:
        state = _from_safe(torch.load(path, map_location="cpu", weights_only=True))
        if check is not None:
            check(state)
        for name, part in dict(parts).items():
            part.load_state_dict(state[name])
    except ConfigError:
        raise
    except pickle.UnpicklingError:  # torch's advice there is to load unsafely: not ours to give
        raise ConfigError(f"{path} is not a checkpoint this project wrote (it holds objects that could run "
                          "code when loaded); not loaded") from None
    except Exception as e:
        raise ConfigError(f"cannot read {path}: {first_line(e)}") from None
    return state


def save_model(run_dir, agent, disc, args):
    """model.pt: the actor, the critics and the discriminator (None for BC and the teacher), with what
    rebuilds the actor (env, hidden sizes, observation features); evaluate.py plays it back."""
    model = {"actor": agent.actor, "critic": agent.critic} | ({"discriminator": disc} if disc is not None else {})
    save_checkpoint(os.path.join(run_dir, "model.pt"), model, env=args.env, hidden=args.hidden,
                    time_feature=args.time_feature, absorbing=args.absorbing)


def check_finite(losses, where, run_dir):
    """ConfigError if a loss is NaN or infinite: the run stops before a diverged policy acts again."""
    bad = {k: float(v) for k, v in losses.items() if not math.isfinite(float(v))}
    if bad:
        kept = (f"the last good checkpoint in {run_dir} is kept" if os.path.isfile(os.path.join(run_dir, "checkpoint.pt"))
                else "it had written no checkpoint yet")
        raise ConfigError(f"non-finite loss {bad} {where}; stopped, {kept}")


class RNGs:
    """Every RNG a run draws from, as a checkpoint part: numpy's Generator, torch's CPU (and
    CUDA) generators."""

    def __init__(self, rng):
        self.rng = rng

    def state_dict(self):
        import torch
        return {"numpy": self.rng.bit_generator.state, "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}

    def load_state_dict(self, state):
        import torch
        self.rng.bit_generator.state = state["numpy"]
        torch.set_rng_state(state["torch"])
        if state["cuda"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda"])


def run_folder_config(parser, run_dir):
    """The config.json of a results script's RUN_DIR, a run folder made by sail.py with its checkpoint.pt,
    as a dict; a folder without them, or an unreadable config, is the parser's one error line (exit 2)."""
    for name in ("config.json", "checkpoint.pt"):
        if not os.path.isfile(os.path.join(run_dir, name)):
            parser.error(f"{run_dir} has no {name}: give a run folder made by sail.py")
    try:
        return vars(read_config(run_dir))
    except ConfigError as e:
        parser.error(str(e))


def run_folder_checkpoint(parser, run_dir, parts=()):
    """load_checkpoint on RUN_DIR's checkpoint.pt, an unreadable one the parser's one error line (exit 2)."""
    try:
        return load_checkpoint(os.path.join(run_dir, "checkpoint.pt"), parts)
    except ConfigError as e:
        parser.error(str(e))


# ---------------------------------------------------------------------------------------------
# --resume and stopping
# ---------------------------------------------------------------------------------------------

def read_config(run_dir):
    """A run folder's config.json as a namespace of its flags."""
    path = os.path.join(run_dir, "config.json")
    try:
        with open(path) as f:
            return argparse.Namespace(**json.load(f))
    except (OSError, ValueError, TypeError) as e:
        raise ConfigError(f"cannot read {path}: {first_line(e)}") from None


# flags that have left sail.py, with the value today's code always runs: a saved run with another cannot resume
RETIRED_FLAGS = {"update_every": 1, "noise_color": 0.0, "actor_lr": None, "disc_fall_margin": 0, "utd": 1,
                 "return_bonus_of": "return"}


def resume_config(run_dir, args, given, changeable, script):
    """The saved run's flags, with the `changeable` ones taken anew where given on the command
    line. Any other flag given is a ConfigError: a resumed run cannot honour it, nor can `script`
    resume another script's run."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isfile(path):
        raise ConfigError(f"--resume {run_dir}: no config.json there (not a run folder)")
    if not os.path.isfile(os.path.join(run_dir, "checkpoint.pt")):
        raise ConfigError(f"--resume {run_dir}: no checkpoint.pt there (the run stopped before its first "
                          "checkpoint); start it again")
    config = vars(read_config(run_dir))
    if config.get("script", script) != script:
        raise ConfigError(f"--resume {run_dir}: a run of {config['script']}, not of {script}")
    ignored = sorted(given - set(changeable) - {"resume"})
    if ignored:
        flags = ", ".join("--" + name.replace("_", "-") for name in ignored)
        allowed = ", ".join("--" + name.replace("_", "-") for name in changeable)
        raise ConfigError(f"--resume keeps the run's saved flags; {flags} cannot change (only {allowed} can)")
    # a flag today's parser has and the saved run lacks (older code) would take today's default: refused
    missing = sorted(set(vars(args)) - set(config) - {"given", "resume", "output_dir", *changeable})
    if missing:
        flags = ", ".join("--" + name.replace("_", "-") for name in missing)
        raise ConfigError(f"--resume {run_dir}: its config.json has no {flags} (a run of older code); start it anew")
    # a flag that has left the code, saved with a value other than the one the code now always runs
    changed = sorted(k for k, v in RETIRED_FLAGS.items() if config.get(k, v) != v)
    if changed:
        raise ConfigError(f"--resume {run_dir}: it was made with " + ", ".join(
            f"--{k.replace('_', '-')} {config[k]}" for k in changed) + ", which this code no longer has")
    saved = {k: v for k, v in config.items() if k in vars(args)}  # the command line, the commit: not flags
    anew = {name: getattr(args, name) for name in changeable if name in given}
    return argparse.Namespace(**(vars(args) | saved | anew | {"resume": run_dir}))


def record_resume(run_dir, args, global_step, changeable):
    """Once a resumed run's checkpoint has loaded (so that a refused --resume leaves the folder as it
    was): refuses a --total-timesteps below the steps already taken, and writes into config.json the
    `changeable` flags as the run now has them, e.g. the 1M steps it was extended to."""
    if args.total_timesteps < global_step:
        raise ConfigError(f"--resume {run_dir}: --total-timesteps {args.total_timesteps} is below the "
                          f"{global_step} steps the run has taken")
    if args.total_timesteps == global_step:
        raise ConfigError(f"--resume {run_dir}: the run has finished its {global_step} steps; give a larger "
                          "--total-timesteps to continue it")
    lock_run_dir(run_dir)
    config = vars(read_config(run_dir))
    now = {name: getattr(args, name) for name in changeable}
    if any(config.get(name) != value for name, value in now.items()):
        atomic_write(os.path.join(run_dir, "config.json"),
                     lambda f: f.write(json.dumps(config | now, indent=2).encode()))
    print(f"resumed {run_dir} at step {global_step} of {args.total_timesteps}", flush=True)


class StopRequest:
    """Turns SIGINT (Ctrl-C) and SIGTERM (kill, timeout, job schedulers) into a flag that the
    training loop reads once per step, so that it stops between steps and checkpoints.

        with StopRequest() as stop:
            while ... and not stop.requested: ...
    """

    def __enter__(self):
        self.requested, self.signal = False, None
        self._previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def _handle(self, signum, frame):
        self.requested, self.signal = True, signum

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    @property
    def exit_code(self):
        """The shell's convention: 128 + the signal's number (130 for Ctrl-C, 143 for SIGTERM)."""
        return 128 + self.signal if self.requested else 0
