"""The discriminator D(s, a) of SAIL (paper, "Off-Policy Adversarial TD Learning"), also GAIL's.

D tells the teacher buffer R_E (label 1) from the agent's own transitions (label 0), trained by
Eq. (4) with an entropy bonus and a gradient penalty, on states (and optionally actions)
normalised by their running statistics, as in the authors' code. Its output becomes the
learner's per-step reward, r'(s, a) = -log(1 - D(s, a)).
"""

import torch
import torch.nn as nn
import torch.nn.functional as F

from td3 import mlp


class RunningNorm(nn.Module):
    """Normalises inputs by the running mean and variance of the data seen so far
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
        # hardly looks at them; on the same scale they weigh as much as the states
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
    """Eq. (4) as a cross-entropy to minimise, minus an entropy bonus, plus a gradient penalty.
    Returns the loss and D's mean output on the teacher and on the self samples."""
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


def train_discriminator(disc, optimizer, teacher_buffer, self_buffer, steps, batch_size, entropy_coef, grad_penalty,
                        recent_window=None):
    """`steps` minibatches of Eq. (4): `batch_size` samples of R_E labelled 1 and as many of R_B
    labelled 0 (with `recent_window`, of R_B's most recent transitions: the on-policy D)."""
    device = disc.obs_norm.mean.device
    for _ in range(steps):
        t_obs, t_act, *_ = teacher_buffer.sample(batch_size)
        if recent_window is not None:
            b_obs, b_act, *_ = self_buffer.sample_recent(batch_size, recent_window)
        else:
            b_obs, b_act, *_ = self_buffer.sample(batch_size)
        t_obs, t_act, b_obs, b_act = (x.to(device) for x in (t_obs, t_act, b_obs, b_act))
        disc.update_norms(torch.cat([t_obs, b_obs]), torch.cat([t_act, b_act]))
        loss, d_teacher, d_self = discriminator_loss(disc, t_obs, t_act, b_obs, b_act, entropy_coef, grad_penalty)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return {"disc_loss": loss.detach(), "disc_teacher": d_teacher.detach(), "disc_self": d_self.detach()}


def shaped_reward(disc, obs, actions, kind):
    """r'(s, a) of a batch from the current D: kind "sail" is the paper's -log(1 - D), "airl" DAC's
    log D - log(1 - D)."""
    with torch.no_grad():
        logit = disc(disc.inputs(obs, actions))
    if kind == "sail":
        return F.softplus(logit)  # -log(1 - D) = -log(1 - sigmoid(x)) = softplus(x), no overflow
    return logit  # airl: log D - log(1 - D) = x
