"""Colored action noise: Gaussian exploration noise correlated across env steps.

TD3 explores with white noise, a fresh Gaussian draw at every step; on a 1000-step episode its
pushes average out within a few steps. Colored noise has a power spectrum that falls as 1/f^beta
along the episode's steps: beta = 0 is white noise, beta = 2 red (Brownian, close to the
Ornstein-Uhlenbeck noise of DDPG), beta = 1 pink, between the two. Eberhard et al. (2023), "Pink
Noise Is All You Need: Colored Noise Exploration in Deep Reinforcement Learning" (ICLR), found pink
noise better than white and red across continuous-control tasks. Each entry keeps a unit variance
whatever beta, so --exploration-noise keeps its meaning as the noise's std.

A run's noise is a stream of such sequences, one per block of env steps as long as the time limit,
each drawn whole from a generator seeded by the run's seed and the block's number: a resumed run draws
the same noise without keeping it in its checkpoint, and the run's other random draws are unchanged.
"""

import numpy as np


def colored_noise(beta, steps, dim, rng):
    """(steps, dim) Gaussian noise, unit variance per entry, power spectrum ~ 1/f^beta along axis 0."""
    freqs = np.fft.rfftfreq(steps)
    freqs[0] = freqs[1]  # the mean's power: that of the lowest frequency, not infinite
    amplitude = freqs ** (-beta / 2)
    real, imag = rng.standard_normal((2, len(freqs), dim))
    imag[0] = 0.0  # the mean is real; with an even length, so is the highest frequency
    real[0] *= np.sqrt(2)
    if steps % 2 == 0:
        imag[-1], real[-1] = 0.0, real[-1] * np.sqrt(2)
    # each frequency but those two appears twice in the full spectrum (as its conjugate)
    power = 2 * (amplitude ** 2).sum() - amplitude[0] ** 2 - (amplitude[-1] ** 2 if steps % 2 == 0 else 0.0)
    noise = np.fft.irfft(amplitude[:, None] * (real + 1j * imag), n=steps, axis=0)
    return noise * steps / np.sqrt(2 * power)


class ColoredNoise:
    """An env's action noise, one entry per action dimension, in blocks of its time limit (envs.make_env's
    `max_episode_steps`): the unit noise of env step `step` is row step % steps of block step // steps."""

    def __init__(self, beta, env, seed):
        self.beta, self.steps, self.dim, self.seed = beta, env.max_episode_steps, env.action_space.shape[0], seed
        self.block, self.sequence = None, None

    def __call__(self, step):
        if step // self.steps != self.block:
            self.block = step // self.steps
            rng = np.random.default_rng([self.seed, self.block])
            self.sequence = colored_noise(self.beta, self.steps, self.dim, rng)
        return self.sequence[step % self.steps]
