"""Plays a run's saved actor back: its scores on the dense return, and optionally a video.

    python evaluate.py runs/Hopper-v5__sail__1__20261121-120000 --episodes 10
    python evaluate.py RUN_DIR --video hopper.gif          # render the episodes headless

Every run of sail.py, bc.py (and make_demos.py --save-teacher) writes model.pt at its end and
sail.py keeps its actor in checkpoint.pt, so a run still in progress can be watched too. The env
and the actor are rebuilt from the run's config.json; the episodes are played with the
deterministic policy on an env seeded with --seed (with --noise STD, the actor plus Gaussian
noise as in training: how its training episodes score against the promotion bar).
"""

import os
import sys

import plumbing

if __name__ == "__main__":
    plumbing.quiet_interrupt_while_importing("evaluate.py")

import numpy as np
import torch

from envs import make_env, rollout
from plumbing import ConfigError, non_negative_float, positive_int
from td3 import TD3


def parse_args(argv=None):
    p = plumbing.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (config.json with model.pt or checkpoint.pt)")
    p.add_argument("--episodes", type=positive_int, default=5, help="episodes to play")
    p.add_argument("--seed", type=plumbing.seed, default=1, help="seed of the env (and of --noise)")
    p.add_argument("--threads", type=plumbing.threads, default=2, help="torch CPU threads")
    p.add_argument("--video", metavar="FILE", help="render the episodes headless into FILE (.gif, or .mp4 with "
                   "imageio-ffmpeg)")
    p.add_argument("--noise", type=non_negative_float, default=0.0, help="std of Gaussian action noise, as "
                   "--exploration-noise in training (0: deterministic)")
    return p.parse_args(argv)


def evaluate_run(run_dir, episodes, seed, threads, video=None, noise=0.0):
    """Plays `episodes` episodes of RUN_DIR's saved actor (the newer of model.pt and checkpoint.pt) on an env
    seeded with `seed`; prints the return and length of each, then their mean. With `video` (a .gif
    or .mp4 path) the episodes are rendered headless into it, one after another."""
    if video is not None:
        check_video_path(video)
        os.environ.setdefault("MUJOCO_GL", "egl")  # headless; MUJOCO_GL=osmesa where EGL is missing
    if not os.path.isfile(os.path.join(run_dir, "config.json")):
        raise ConfigError(f"{run_dir}: no config.json there (not a run folder)")
    config = plumbing.read_config(run_dir)
    script = getattr(config, "script", "sail.py")
    if script not in ("sail.py", "bc.py", "make_demos.py"):
        raise ConfigError(f"{run_dir}: a run of {script}; evaluate.py plays the actors of sail.py, bc.py and "
                          "make_demos.py --save-teacher")
    saved_files = [p for p in (os.path.join(run_dir, n) for n in ("model.pt", "checkpoint.pt")) if os.path.isfile(p)]
    if not saved_files:
        raise ConfigError(f"{run_dir}: no model.pt or checkpoint.pt there")
    path = max(saved_files, key=os.path.getmtime)  # a stopped run resumed since: its checkpoint is newer than model.pt
    saved = plumbing.load_checkpoint(path)  # on the CPU, also a run made with --device cuda
    torch.set_num_threads(threads)
    try:
        env = make_env(config.env, seed, time_feature=config.time_feature, absorbing=config.absorbing,
                       render_mode="rgb_array" if video else None)
    except AttributeError as e:
        raise ConfigError(f"{run_dir}/config.json lacks {e.name}: not a run folder of sail.py or bc.py") from None
    if video is not None:
        follow_the_body(env)
    agent = TD3(env.observation_space.shape[0], env.action_space.shape[0], env.action_space.low,
                env.action_space.high, hidden=config.hidden)
    try:
        agent.actor.load_state_dict(saved["actor"] if "actor" in saved else saved["agent"]["actor"])
    except (RuntimeError, KeyError, TypeError) as e:  # config.json and the saved networks disagree (sizes, env)
        raise ConfigError(f"{path} does not fit {run_dir}/config.json: {plumbing.first_line(e)}") from None
    returns, frames, fps = [], [], env.metadata.get("render_fps", 30)
    rng = np.random.default_rng(seed)
    for i in range(episodes):
        episode_frames = [] if video else None
        try:
            episode = rollout(env, agent.act if not noise else lambda o: agent.explore(o, noise, rng), episode_frames)
        except Exception as e:  # no OpenGL: EGL or OSMesa missing or broken
            if video is None:
                raise
            raise ConfigError(f"cannot render {config.env} (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): "
                              f"{plumbing.first_line(e)}") from None
        if video is not None:  # what the video keeps, episode by episode (a 480x480 frame is 0.7 MB)
            frames += kept_frames(video, episode_frames, fps)
        returns.append(episode["episodic_return"])
        print(f"episode {i + 1}: return {returns[-1]:.1f}, length {episode['length']}")
    print(f"{config.env}, {path}: mean return {np.mean(returns):.1f} +- {np.std(returns):.1f} "
          f"over {len(returns)} episodes (env seed {seed}{f', exploration noise {noise:g}' if noise else ''})")
    if video is not None:
        write_video(video, frames, fps)
        print(f"wrote {video}: {len(frames)} frames")
    return 0


def follow_the_body(env):
    """Makes the camera follow the body that the env's camera config names. Gymnasium 1.4's
    MuJoCo envs (Hopper, Walker2d, HalfCheetah, ...) render through a free camera, which ignores
    the config's trackbodyid: a hopper that hops well leaves the picture after a second."""
    renderer = getattr(env.unwrapped, "mujoco_renderer", None)
    config = getattr(renderer, "default_cam_config", None) or {}
    if "trackbodyid" in config and renderer.camera_id == -1:
        import mujoco
        renderer.default_cam_config = config | {"type": mujoco.mjtCamera.mjCAMERA_TRACKING}
        renderer.camera_id = None  # else every render() sets the camera back to free


def check_video_path(path):
    """Before anything runs: a .gif or .mp4 path that can be written (mp4 needs imageio-ffmpeg)."""
    if not path.endswith((".gif", ".mp4")):
        raise ConfigError(f"--video {path}: give a .gif or .mp4 file")
    if path.endswith(".mp4"):
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ConfigError("--video *.mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); .gif needs nothing more")
    plumbing.check_writable(path)


def gif_frames(fps):
    """(stride, delay in ms) of a GIF at about real time: GIF delays are whole hundredths of a
    second, and browsers play any delay under 20 ms as 100 ms, so MuJoCo's 125 frames/s become
    every 5th frame at 40 ms."""
    stride = max(1, round(fps / 25))
    return stride, 10 * max(2, round(100 * stride / fps))


def kept_frames(path, frames, fps):
    """The frames of one episode that a video keeps: a GIF every stride-th at half the width
    and height (a 1000-step Hopper episode in about 1 MB), an MP4 every frame."""
    if path.endswith(".gif"):
        stride, _ = gif_frames(fps)
        return [frame[::2, ::2] for frame in frames[::stride]]
    return frames


def write_video(path, frames, fps):
    """Writes kept_frames' frames as a GIF or MP4, atomically."""
    import imageio.v3 as iio
    if path.endswith(".gif"):
        _, delay = gif_frames(fps)
        plumbing.atomic_write(path, lambda f: iio.imwrite(f, np.stack(frames), extension=".gif", duration=delay,
                                                           loop=0))
    else:
        plumbing.atomic_write(path, lambda f: iio.imwrite(f, np.stack(frames), extension=".mp4", fps=fps))


if __name__ == "__main__":
    args = parse_args()
    sys.exit(plumbing.run_main("evaluate.py", lambda a: evaluate_run(a.run_dir, a.episodes, a.seed, a.threads,
                                                                    a.video, a.noise), args))
