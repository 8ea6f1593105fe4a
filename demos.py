"""Demonstration files: the teacher's episodes on disk, and R_E built from them.

A demo file is an .npz of flat arrays over all its episodes (the format is in README.md);
`load_demos` checks it against the env, so a wrong or damaged file is one clear error before
training starts. A Minari dataset (its folder, or its id in the local Minari store) can stand in
for a demo file. Writes are atomic: an interrupted make_demos.py leaves no broken file.
"""

import os
import shutil
import tempfile
import warnings

import numpy as np

from buffers import TeacherBuffer
from envs import add_features
from plumbing import ConfigError, atomic_write, first_line

DEMO_KEYS = ("observations", "actions", "next_observations", "rewards", "terminations",
             "truncations", "episode_lengths", "episode_returns", "env_id")



def save_demos(path, episodes, env_id):
    """Writes a demo file atomically (temp file, then rename).

    `episodes` is a list of dicts as envs.rollout returns them: raw (feature-free) arrays
    observations, actions, next_observations, rewards (dense), the bools terminated / truncated
    for the episode, and its episodic_return.
    """
    lengths = np.array([len(ep["actions"]) for ep in episodes], dtype=np.int64)
    data = {
        "observations": np.concatenate([ep["observations"] for ep in episodes]).astype(np.float32),
        "actions": np.concatenate([ep["actions"] for ep in episodes]).astype(np.float32),
        "next_observations": np.concatenate([ep["next_observations"] for ep in episodes]).astype(np.float32),
        "rewards": np.concatenate([ep["rewards"] for ep in episodes]).astype(np.float32),
        "terminations": np.concatenate([_last_flag(n, ep["terminated"]) for n, ep in zip(lengths, episodes)]),
        "truncations": np.concatenate([_last_flag(n, ep["truncated"]) for n, ep in zip(lengths, episodes)]),
        "episode_lengths": lengths,
        "episode_returns": np.array([ep["episodic_return"] for ep in episodes], dtype=np.float64),
        "env_id": np.array(env_id),
        "gymnasium_version": np.array(_version("gymnasium")),
        "mujoco_version": np.array(_version("mujoco")),
    }
    atomic_write(path, lambda f: np.savez_compressed(f, **data))


def default_demo_path(env_id):
    """demos/<env>.npz beside this file: the shipped teacher demonstrations."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "demos", f"{env_id}.npz")


def load_demos(path, env_id, obs_dim, act_dim, num_demos=None):
    """Reads and checks demonstrations; returns a list of episode dicts (the first `num_demos`).

    `path` is a demo file (.npz, format in README.md) or a Minari dataset: its folder, or its
    id in the local Minari store (e.g. mujoco/hopper/medium-v0). Each episode: observations,
    actions, next_observations, rewards (raw float32 arrays), terminated (bool),
    episodic_return (float). Any problem raises ConfigError naming the source.
    """
    if os.path.isfile(path):
        try:
            with np.load(path, allow_pickle=False) as f:
                data = {k: f[k] for k in f.files}
        except Exception as e:  # not a zip, a damaged one (zlib), a plain .npy array, ...
            raise ConfigError(f"demo file {path} is not a readable .npz file ({first_line(e)})") from None
    elif os.path.isdir(path) or not path.endswith(".npz"):
        data = read_minari(path)
    else:
        raise ConfigError(f"demo file {path} not found (make one with make_demos.py --env {env_id})")
    missing = [k for k in DEMO_KEYS if k not in data]
    if missing:
        raise ConfigError(f"demo file {path} lacks {', '.join(missing)}")
    not_numbers = [k for k in DEMO_KEYS if k != "env_id" and (np.ndim(data[k]) == 0 or not (
        np.issubdtype(data[k].dtype, np.number) or data[k].dtype == bool))]
    if not_numbers:
        raise ConfigError(f"demo file {path}: {', '.join(not_numbers)} must be arrays of numbers")
    file_env = str(data["env_id"])
    n = len(data["actions"])
    if file_env != env_id:
        raise ConfigError(f"demo file {path} holds demonstrations for {file_env}, not {env_id}")
    for key in ("observations", "next_observations"):
        if data[key].ndim != 2 or data[key].shape[1] != obs_dim:
            raise ConfigError(f"demo file {path}: {key} have shape {data[key].shape}, "
                              f"{env_id} has {obs_dim}-dim observations")
    if data["actions"].ndim != 2 or data["actions"].shape[1] != act_dim:
        raise ConfigError(f"demo file {path}: actions have shape {data['actions'].shape}, "
                          f"{env_id} has {act_dim}-dim actions")
    lengths = data["episode_lengths"].astype(np.int64)
    same_rows = all(len(data[k]) == n for k in ("observations", "next_observations", "rewards",
                                                    "terminations", "truncations"))
    if not same_rows or lengths.sum() != n or (lengths <= 0).any() or len(data["episode_returns"]) != len(lengths):
        raise ConfigError(f"demo file {path} is inconsistent: arrays and episode_lengths disagree")
    if not all(np.isfinite(data[k]).all() for k in ("observations", "actions", "next_observations", "rewards",
                                                    "episode_returns")):
        raise ConfigError(f"demo file {path} holds NaN or inf values")
    num_demos = len(lengths) if num_demos is None else num_demos
    if num_demos > len(lengths):
        raise ConfigError(f"demo file {path} holds {len(lengths)} episodes, {num_demos} were asked for")
    episodes, start = [], 0
    for length, ret in zip(lengths[:num_demos], data["episode_returns"][:num_demos]):
        sl = slice(start, start + length)
        episodes.append({
            "observations": data["observations"][sl], "actions": data["actions"][sl],
            "next_observations": data["next_observations"][sl], "rewards": data["rewards"][sl],
            "terminated": bool(data["terminations"][sl][-1]), "episodic_return": float(ret),
        })
        start += length
    return episodes


def _minari():
    try:
        import minari
    except ImportError:
        raise ConfigError("Minari datasets need the minari package: pip install -r requirements-extras.txt") from None
    return minari


def read_minari(source):
    """A Minari dataset (folder, or id in the local store; nothing is downloaded) as the arrays of
    a demo file. Minari keeps N+1 observations for an episode of N actions: observation t and
    t+1 make transition t."""
    try:
        minari = _minari()
    except ConfigError:
        if os.path.isdir(source):
            raise
        raise ConfigError(f"{source} is not a demo file; as a Minari dataset id, it needs the minari package "
                          "(pip install -r requirements-extras.txt)") from None
    try:
        if os.path.isdir(source):
            data_dir = os.path.join(source, "data") if os.path.isdir(os.path.join(source, "data")) else source
            dataset = minari.MinariDataset(data_dir)
        else:
            dataset = minari.load_dataset(source)
        episodes = list(dataset.iterate_episodes())
    except Exception as e:
        where = "is a folder but not a Minari dataset" if os.path.isdir(source) else \
            "is neither a demo file nor a dataset in the local Minari store"
        raise ConfigError(f"{source} {where} ({first_line(e)})") from None
    if not episodes or not all(isinstance(ep.observations, np.ndarray) for ep in episodes):
        raise ConfigError(f"Minari dataset {source} has no episodes with flat array observations")
    cat = lambda parts, dtype: np.concatenate(parts).astype(dtype)  # noqa: E731
    return {
        "observations": cat([ep.observations[:-1] for ep in episodes], np.float32),
        "next_observations": cat([ep.observations[1:] for ep in episodes], np.float32),
        "actions": cat([ep.actions for ep in episodes], np.float32),
        "rewards": cat([ep.rewards for ep in episodes], np.float32),
        "terminations": cat([ep.terminations for ep in episodes], bool),
        "truncations": cat([ep.truncations for ep in episodes], bool),
        "episode_lengths": np.array([len(ep.actions) for ep in episodes], dtype=np.int64),
        "episode_returns": np.array([np.sum(ep.rewards, dtype=np.float64) for ep in episodes]),
        "env_id": np.array(dataset.env_spec.id if dataset.env_spec is not None else ""),
    }


def check_minari_id(dataset_id):
    """Before any training: ConfigError unless `dataset_id` has Minari's form and is new in the local store."""
    minari = _minari()
    from minari.dataset.minari_dataset import DATASET_ID_RE
    match = DATASET_ID_RE.fullmatch(dataset_id)
    if match is None or match.group("version") is None:
        raise ConfigError(f"--minari {dataset_id}: a Minari dataset id has the form [namespace/]name-vN, "
                          "e.g. sail/hopper/teacher-v0")
    if dataset_id in minari.list_local_datasets():
        raise ConfigError(f"the Minari dataset {dataset_id} exists already in the local store")


def save_minari(dataset_id, episodes, env_id):
    """Writes episodes (dicts as envs.rollout returns them) as a Minari dataset in the local store. Minari
    writes it in a staging store beside the real one, from where it moves in whole: an interrupted write
    leaves no half-written dataset in the store."""
    minari = _minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer
    from minari.storage.datasets_root_dir import get_dataset_path
    buffers = [EpisodeBuffer(observations=np.concatenate([ep["observations"], ep["next_observations"][-1:]]),
                             actions=np.asarray(ep["actions"]), rewards=list(ep["rewards"]),
                             terminations=[False] * (len(ep["actions"]) - 1) + [ep["terminated"]],
                             truncations=[False] * (len(ep["actions"]) - 1) + [ep["truncated"]])
               for ep in episodes]
    store = os.path.abspath(get_dataset_path())
    staging = tempfile.mkdtemp(prefix=".minari-staging-", dir=os.path.dirname(store))  # same file system
    store_variable = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = staging
    try:
        with warnings.catch_warnings():  # minari asks for author, e-mail, code links: not known here
            warnings.simplefilter("ignore", UserWarning)
            minari.create_dataset_from_buffers(
                dataset_id, buffers, env=env_id, eval_env=env_id, algorithm_name="make_demos.py (TD3 teacher)",
                description=f"{len(episodes)} episodes of a sub-optimal TD3 teacher on {env_id}, recorded by make_demos.py")
        target = os.path.join(store, dataset_id)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        os.rename(os.path.join(staging, dataset_id), target)  # refuses a dataset there already
    except Exception as e:  # e.g. the id was taken meanwhile
        raise ConfigError(f"cannot write the Minari dataset {dataset_id}: {first_line(e)}") from None
    finally:
        if store_variable is None:
            os.environ.pop("MINARI_DATASETS_PATH")
        else:
            os.environ["MINARI_DATASETS_PATH"] = store_variable
        shutil.rmtree(staging, ignore_errors=True)


def _last_flag(length, flag):
    flags = np.zeros(length, dtype=bool)
    flags[-1] = flag
    return flags


def _version(package):
    from importlib.metadata import version
    return version(package)


def load_teacher_buffer(path, env_id, env, num_demos, capacity, time_feature, absorbing, keep="return"):
    """R_E from the first `num_demos` episodes of a demo file, with the same observation
    features (time, absorbing state) that `env`'s wrappers add online; `keep`: TeacherBuffer's."""
    raw_obs_dim = env.observation_space.shape[0] - int(time_feature) - int(absorbing)
    teacher_buffer = TeacherBuffer(capacity, keep)
    featured = [(episode["episodic_return"], add_features(episode, env.max_episode_steps, time_feature, absorbing))
                for episode in load_demos(path, env_id, raw_obs_dim, env.action_space.shape[0], num_demos)]
    demo_steps = sum(len(data[0]) for _, data in featured)
    if demo_steps > capacity:  # R_E would drop demos as it loads them
        raise ConfigError(f"--teacher-capacity {capacity} is smaller than the {len(featured)} demo episodes "
                          f"({demo_steps} transitions)")
    for episodic_return, data in featured:
        teacher_buffer.add_episode(episodic_return, *data)
    return teacher_buffer
