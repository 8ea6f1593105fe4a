"""Per-step credit from the episodic return: what the sparse env's one number per episode can
tell the critic about single steps. Both are additions of this repo to the paper's SAIL.

- The return bonus (IRCR, Gangwani et al. 2020): every step is credited with its episode's
  return scaled to [0, 1] by the lowest and highest returns seen. D's reward only says "look
  like R_E"; the bonus tells the critic which of the agent's own episodes were better.
- The return decomposition (RRD, Ren et al. 2022): a per-step reward r(s, a, s') learned so that
  its mean over an episode fits the episode's return per step, a credit that differs between
  the steps of one episode; with a learned action cost c ||a||^2, c >= 0, beside it.
"""

import torch
import torch.nn as nn
import torch.nn.functional as F

from td3 import mlp


def return_bonus(episode_returns, return_range):
    """IRCR's guidance reward: each transition's episodic return mapped to [0, 1] by the lowest
    and highest returns seen (R_E's included)."""
    low, high = return_range
    return (episode_returns - low) / max(high - low, 1e-8)


class RewardModel(nn.Module):
    """r(s, a, s'), a per-step reward learned from episodic returns alone (RRD; inputs s, a and the
    change of state, as in github.com/Stilwell-Git/Randomized-Return-Decomposition).

    With `learn_action_cost`, minus a learned quadratic cost of the action, c ||a||^2 with c >= 0, the
    form of the control cost in gymnasium's locomotion rewards. The network alone, fitted to episode
    sums, learns only a fraction of what actions cost (it reads a large action as the speed it makes);
    the explicit term lets the returns' differences set c. c starts near 0 (0.0025) and stays there
    where the returns do not ask for it."""

    # Adam moves a parameter by at most its step size per minibatch, and c's parameter has about 5 to go
    # on Ant-v5 (c from 0.0025 to 0.4): at the networks' 3e-4 that takes tens of thousands of minibatches
    ACTION_COST_LR = 1e-2

    def __init__(self, obs_dim, act_dim, hidden, learn_action_cost=False):
        super().__init__()
        self.net = mlp([2 * obs_dim + act_dim, *hidden, 1], nn.ReLU)
        self.register_parameter("action_cost_rho", nn.Parameter(torch.tensor(-6.0)) if learn_action_cost else None)

    def action_cost(self):
        """c = softplus(rho) >= 0, the weight of the squared action norm (0 without `learn_action_cost`)."""
        if self.action_cost_rho is None:
            return self.net[0].weight.new_zeros(())
        return F.softplus(self.action_cost_rho)

    def parameter_groups(self, lr):
        """Adam's parameter groups: the network at `lr`, c's parameter at ACTION_COST_LR."""
        groups = [{"params": list(self.net.parameters()), "lr": lr}]
        if self.action_cost_rho is not None:
            groups.append({"params": [self.action_cost_rho], "lr": self.ACTION_COST_LR})
        return groups

    def forward(self, obs, actions, next_obs):
        reward = self.net(torch.cat([obs, actions, next_obs - obs], dim=-1)).squeeze(-1)
        if self.action_cost_rho is not None:
            reward = reward - self.action_cost() * actions.pow(2).sum(-1)
        return reward


def train_reward_model(reward_model, optimizer, self_buffer, batch_size, subset_size):
    """One minibatch of randomized return decomposition: for batch_size / subset_size (at least one)
    finished episodes of R_B, the mean of r over `subset_size` random steps (an unbiased estimate of the mean
    over all steps) is fitted to the episodic return over the episode's length (RRD's loss, per step)."""
    device = next(reward_model.parameters()).device
    num_episodes = max(1, batch_size // subset_size)
    obs, actions, next_obs, mask, returns, lengths = (
        x.to(device) for x in self_buffer.sample_episode_subsets(num_episodes, subset_size))
    per_step = reward_model(obs, actions, next_obs)
    estimate = (per_step * mask).sum(1) / mask.sum(1).clamp_min(1.0)
    loss = F.mse_loss(estimate, returns / lengths.clamp_min(1))
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    stats = {"decomposition_loss": loss.detach()}
    if reward_model.action_cost_rho is not None:
        stats["decomposition_action_cost"] = reward_model.action_cost().detach()
    return stats


def decomposition_unit(kind, return_range, rate_range, episode_steps):
    """The learned reward's unit, about 1 per step of the best episode seen over the worst: "rate",
    the range of returns per step (return / length) seen; "range" (RRD's own scale), the range of
    returns seen over the env's time limit, which lets r outweigh D's reward where episodes end early."""
    if kind == "rate":
        return max(rate_range[1] - rate_range[0], 1e-8)
    return max(return_range[1] - return_range[0], 1e-8) / episode_steps
