"""TD3 (Fujimoto, van Hoof, Meger 2018): the learner of both the teacher and SAIL.

The update takes the reward of a batch from its caller: the dense env reward when the teacher
is trained (make_demos.py), the discriminator reward r'(s, a) in SAIL (sail.py). Everything
else is the TD3 paper's algorithm: twin critics with the minimum of both as target (clipped
double Q), target policy smoothing, delayed actor updates and Polyak-averaged target networks.

Written for speed on a CPU without hiding the algorithm: the two critics are one ensemble
whose layers are evaluated with one batched matmul; the actor step reads the critic through
detached weights, so no gradient flows into (or has to be cleared from) the critic; target
networks are updated with one in-place foreach lerp; Adam is the fused implementation.
"""

import copy
import math

import torch
import torch.nn as nn
import torch.nn.functional as F


class Actor(nn.Module):
    """Deterministic policy: MLP with ReLU, tanh output scaled to the action bounds."""

    def __init__(self, obs_dim, act_dim, hidden, action_low, action_high):
        super().__init__()
        layers, d = [], obs_dim
        for h in hidden:
            layers += [nn.Linear(d, h), nn.ReLU()]
            d = h
        layers += [nn.Linear(d, act_dim), nn.Tanh()]
        self.net = nn.Sequential(*layers)
        low = torch.as_tensor(action_low, dtype=torch.float32)
        high = torch.as_tensor(action_high, dtype=torch.float32)
        self.register_buffer("action_scale", (high - low) / 2)
        self.register_buffer("action_bias", (high + low) / 2)

    def forward(self, obs):
        return self.net(obs) * self.action_scale + self.action_bias


class TwinCritic(nn.Module):
    """Q1 and Q2 with their layers stacked: weight (2, in, out), bias (2, 1, out).

    One batched matmul per layer evaluates both critics; initialised as nn.Linear would be.
    """

    def __init__(self, obs_dim, act_dim, hidden, num_critics=2):
        super().__init__()
        sizes = [obs_dim + act_dim, *hidden, 1]
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)
            self.weights.append(nn.Parameter(torch.empty(num_critics, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(num_critics, 1, fan_out).uniform_(-bound, bound)))

    def forward(self, obs, action):
        """Both critics: (num_critics, batch)."""
        x = torch.cat([obs, action], dim=-1).expand(len(self.weights[0]), -1, -1)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b, x, w)
            if i < len(self.weights) - 1:
                x = F.relu(x)
        return x.squeeze(-1)

    def q1_detached(self, obs, action):
        """Q1 through detached weights: the actor's gradient without touching critic grads."""
        x = torch.cat([obs, action], dim=-1)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.addmm(b[0].detach(), x, w[0].detach())
            if i < len(self.weights) - 1:
                x = F.relu(x)
        return x.squeeze(-1)


def make_adam(params, lr):
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):  # a device or build without the fused kernel
        return torch.optim.Adam(params, lr=lr, foreach=True)


class TD3:
    def __init__(self, obs_dim, act_dim, action_low, action_high, hidden=(256, 256), lr=3e-4,
                 gamma=0.99, tau=0.005, policy_noise=0.2, noise_clip=0.5, policy_delay=2,
                 device="cpu"):
        self.gamma, self.tau, self.policy_delay = gamma, tau, policy_delay
        self.device = torch.device(device)
        self.actor = Actor(obs_dim, act_dim, hidden, action_low, action_high).to(self.device)
        self.critic = TwinCritic(obs_dim, act_dim, hidden).to(self.device)
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_optimizer = make_adam(self.actor.parameters(), lr)
        self.critic_optimizer = make_adam(self.critic.parameters(), lr)
        # target policy smoothing noise, in units of the action range
        self.policy_noise = policy_noise * self.actor.action_scale
        self.noise_clip = noise_clip * self.actor.action_scale
        self.action_low = torch.as_tensor(action_low, dtype=torch.float32, device=self.device)
        self.action_high = torch.as_tensor(action_high, dtype=torch.float32, device=self.device)
        self.num_updates = 0
        self._online = [*self.actor.parameters(), *self.critic.parameters()]
        self._target = [*self.actor_target.parameters(), *self.critic_target.parameters()]

    @torch.no_grad()
    def act(self, obs):
        """Deterministic action for one observation (numpy in, numpy out)."""
        obs = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        return self.actor(obs.unsqueeze(0))[0].cpu().numpy()

    def update(self, obs, actions, rewards, next_obs, terminated):
        """One TD3 step on a batch; `rewards` come from the caller. Returns detached losses.

        `terminated` is 1 only for true terminal states: a time-limit truncation is not one,
        so the target bootstraps through it.
        """
        with torch.no_grad():
            noise = (torch.randn_like(actions) * self.policy_noise).clamp(-self.noise_clip, self.noise_clip)
            next_actions = (self.actor_target(next_obs) + noise).clamp(self.action_low, self.action_high)
            # clipped double Q: y = r + gamma * (1 - done) * min_i Q'_i(s', a')
            next_q = self.critic_target(next_obs, next_actions).min(dim=0).values
            td_target = rewards + self.gamma * (1.0 - terminated) * next_q
        q = self.critic(obs, actions)
        critic_loss = (q - td_target).pow(2).mean(dim=1).sum()  # both critics' MSE
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()
        self.num_updates += 1
        losses = {"critic_loss": critic_loss.detach(), "q": q[0].mean().detach()}

        if self.num_updates % self.policy_delay == 0:
            actor_loss = -self.critic.q1_detached(obs, self.actor(obs)).mean()
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_optimizer.step()
            with torch.no_grad():  # Polyak averaging: theta' <- (1 - tau) theta' + tau theta
                torch._foreach_lerp_(self._target, self._online, self.tau)
            losses["actor_loss"] = actor_loss.detach()
        return losses

    def state_dict(self):
        return {name: getattr(self, name).state_dict() for name in self._parts} | {"num_updates": self.num_updates}

    def load_state_dict(self, state):
        for name in self._parts:
            getattr(self, name).load_state_dict(state[name])
        self.num_updates = state["num_updates"]

    _parts = ("actor", "critic", "actor_target", "critic_target", "actor_optimizer", "critic_optimizer")
