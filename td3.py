"""TD3 (Fujimoto, van Hoof, Meger 2018): the learner of both the teacher and SAIL.

The update takes the reward of a batch from its caller: the dense env reward when the teacher
is trained (make_demos.py), the discriminator reward r'(s, a) in SAIL (sail.py). Everything
else is the TD3 paper's algorithm: twin critics with the minimum of both as target (clipped
double Q), target policy smoothing, delayed actor updates and Polyak-averaged target networks.
Two options beside it: LayerNorm in the critics (as RLPD), and a caller's term in the actor's
loss (`actor_penalty`, a known cost of the action charged beside Q).

Plain PyTorch: nn.Sequential networks, Adam. Three cheap habits keep it fast on a CPU: the actor
step reads the critic with its parameters frozen (no critic gradient is computed), the target
networks move with one in-place foreach lerp, and Adam runs its fused kernel. A faster matmul
library, where one measures faster, is swapped in from outside (cpu_kernels.py).
"""

import copy

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


def mlp(sizes, activation=nn.ReLU, layer_norm=False):
    """nn.Linear layers of the given sizes with `activation` between them (none at the end);
    with `layer_norm`, a LayerNorm before each activation."""
    layers = []
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(fan_in, fan_out))
        if i < len(sizes) - 2:
            layers += [nn.LayerNorm(fan_out), activation()] if layer_norm else [activation()]
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy pi(s): MLP with ReLU, tanh output scaled to the action bounds."""

    def __init__(self, obs_dim, act_dim, hidden, action_low, action_high):
        super().__init__()
        self.net = mlp([obs_dim, *hidden, act_dim])
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_buffer("action_bias", (high + low) / 2)

    def forward(self, obs):
        return torch.tanh(self.net(obs)) * self.action_scale + self.action_bias


class Critic(nn.Module):
    """Q(s, a): MLP with ReLU on the concatenated observation and action (optionally LayerNorm
    in each hidden layer, which bounds the features and so Q's growth off the data, as RLPD's critic)."""

    def __init__(self, obs_dim, act_dim, hidden, layer_norm=False):
        super().__init__()
        self.net = mlp([obs_dim + act_dim, *hidden, 1], layer_norm=layer_norm)

    def forward(self, obs, action):
        return self.net(torch.cat([obs, action], dim=-1)).squeeze(-1)


class TwinCritic(nn.Module):
    """Q1(s, a) and Q2(s, a): two independent critics."""

    def __init__(self, obs_dim, act_dim, hidden, layer_norm=False):
        super().__init__()
        self.q1 = Critic(obs_dim, act_dim, hidden, layer_norm)
        self.q2 = Critic(obs_dim, act_dim, hidden, layer_norm)

    def forward(self, obs, action):
        return self.q1(obs, action), self.q2(obs, action)


def make_adam(params, lr):
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):  # a device or build without the fused kernel
        return torch.optim.Adam(params, lr=lr, foreach=True)


class TD3:
    def __init__(self, obs_dim, act_dim, action_low, action_high, hidden=(256, 256), lr=3e-4,
                 gamma=0.99, tau=0.005, policy_noise=0.2, noise_clip=0.5, policy_delay=2,
                 device="cpu", critic_layer_norm=False):
        self.gamma, self.tau, self.policy_delay = gamma, tau, policy_delay
        self.device = torch.device(device)
        self.actor = Actor(obs_dim, act_dim, hidden, action_low, action_high).to(self.device)
        self.critic = TwinCritic(obs_dim, act_dim, hidden, critic_layer_norm).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = make_adam(self.actor.parameters(), lr)
        self.critic_optimizer = make_adam(self.critic.parameters(), lr)
        # target policy smoothing noise, in units of the action range
        self.policy_noise = policy_noise * self.actor.action_scale
        self.noise_clip = noise_clip * self.actor.action_scale
        self.action_low = torch.as_tensor(action_low, dtype=torch.float32, device=self.device)
        self.action_high = torch.as_tensor(action_high, dtype=torch.float32, device=self.device)
        self.action_bounds = (np.asarray(action_low, np.float32), np.asarray(action_high, np.float32))
        self.num_updates = 0
        self._online_params = [*self.actor.parameters(), *self.critic.parameters()]
        self._target_params = [*self.actor_target.parameters(), *self.critic_target.parameters()]

    def networks(self):
        """Every network of the agent (for cpu_kernels, which swaps their layers' kernels)."""
        return [self.actor, self.critic, self.actor_target, self.critic_target]

    @torch.no_grad()
    def act(self, obs, target=False):
        """Deterministic action for one observation (numpy in, numpy out); with `target`, the
        Polyak-averaged target actor's."""
        obs = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        actor = self.actor_target if target else self.actor
        return actor(obs.unsqueeze(0))[0].cpu().numpy()

    def explore(self, obs, exploration_noise, rng):
        """The actor's action plus Gaussian noise drawn from rng (std: exploration_noise x half the
        action range), clipped to the action bounds."""
        low, high = self.action_bounds
        noise = rng.normal(0.0, exploration_noise * (high - low) / 2)
        return np.clip(self.act(obs) + noise, low, high).astype(np.float32)

    def update(self, obs, actions, rewards, next_obs, terminated, next_action_mask=None, actor_penalty=None):
        """One TD3 step on a batch; `rewards` come from the caller. Returns detached losses.

        `terminated` is 1 only for true terminal states: a time-limit truncation is not one,
        so the target bootstraps through it. `next_action_mask` (0 or 1 per row, optional)
        multiplies the target's next action: 0 where only the zero action exists in s'.
        `actor_penalty` (optional) maps the actor's actions to a per-row cost in the reward's unit
        that the actor's loss charges beside Q: the exact slope of a known immediate cost, which
        Q, nearly flat in the action, would pass on only in part.
        """
        with torch.no_grad():
            noise = (torch.randn_like(actions) * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
            next_actions = (self.actor_target(next_obs) + noise).clamp(self.action_low, self.action_high)
            if next_action_mask is not None:
                next_actions = next_actions * next_action_mask
            # clipped double Q: y = r + gamma * (1 - done) * min_i Q'_i(s', a')
            next_q = torch.min(*self.critic_target(next_obs, next_actions))
            td_target = rewards + self.gamma * (1.0 - terminated) * next_q
        q1, q2 = self.critic(obs, actions)
        critic_loss = F.mse_loss(q1, td_target) + F.mse_loss(q2, td_target)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()
        self.num_updates += 1
        losses = {"critic_loss": critic_loss.detach(), "q": q1.mean().detach()}

        if self.num_updates % self.policy_delay == 0:
            self.critic.requires_grad_(False)  # the actor's gradient passes through a fixed Q1
            policy_actions = self.actor(obs)
            q = self.critic.q1(obs, policy_actions)
            if actor_penalty is not None:
                q = q - actor_penalty(policy_actions)
            actor_loss = -q.mean()
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.critic.requires_grad_(True)
            self.actor_optimizer.step()
            with torch.no_grad():  # Polyak averaging: theta' <- (1 - tau) theta' + tau theta
                torch._foreach_lerp_(self._target_params, self._online_params, self.tau)
            losses["actor_loss"] = actor_loss.detach()
        return losses

    def state_dict(self):
        return {name: getattr(self, name).state_dict() for name in self._parts} | {"num_updates": self.num_updates}

    def load_state_dict(self, state):
        for name in self._parts:
            getattr(self, name).load_state_dict(state[name])
        self.num_updates = state["num_updates"]

    _parts = ("actor", "critic", "actor_target", "critic_target", "actor_optimizer", "critic_optimizer")
