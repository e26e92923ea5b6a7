"""Generalized advantage estimation (paper eq. 3-4; Schulman et al. 2016), bootstrapping through
truncation.

Eq. 3's k-step estimate of the advantage bootstraps from V after k rewards:

    A_t^(k) = sum_{l<k} gamma^l r_{t+l} + gamma^k V(s_{t+k}) - V(s_t)
            = sum_{l<k} gamma^l delta_{t+l},

with the TD residual delta_t = r_t + gamma V(s_{t+1}) - V(s_t) (the V terms telescope). Eq. 4's
GAE is their exponentially weighted average, (1 - lam) sum_k lam^(k-1) A_t^(k), which sums to

    A_t = sum_{l>=0} (gamma lam)^l delta_{t+l},    so    A_t = delta_t + gamma lam A_{t+1},

the recursion computed here backwards over the rollout. lam = 0 gives the one-step estimate
delta_t, lam = 1 the discounted return minus V (Monte Carlo). Where an episode ends at step t the
sum stops (A_{t+1} belongs to the next episode). Which V(s_{t+1}) delta_t bootstraps from depends
on how it ended: a termination (the hopper fell) has no future, so none; a truncation (the time
limit, every Fetch episode) would have gone on, so its true last state's value, like any other
step (the caller passes those values as ``next_values``).
"""

import torch


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    terminations: torch.Tensor,
    episode_ends: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """A_t of eq. 4 for each step of a rollout, all arguments of shape (T, N) (T steps of N envs):
    ``values`` V(s_t); ``next_values`` V(s_{t+1}), the true last state's where an episode ended;
    ``terminations`` 1.0 where the episode terminated, ``episode_ends`` 1.0 (or True) where it
    ended either way."""
    not_terminal, goes_on = 1.0 - terminations, 1.0 - episode_ends.float()
    advantages, lastgaelam = torch.zeros_like(values), torch.zeros_like(values[0])  # A_T = 0
    for t in reversed(range(len(values))):
        delta = rewards[t] + gamma * not_terminal[t] * next_values[t] - values[t]  # delta_t
        lastgaelam = delta + gamma * lam * goes_on[t] * lastgaelam  # eq. 4: A_t, backwards
        advantages[t] = lastgaelam
    return advantages
