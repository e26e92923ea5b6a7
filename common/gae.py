"""Generalized Advantage Estimation (paper eq. 3-4; Schulman et al. 2016).

The k-step advantage estimates of eq. 3 bootstrap from the baseline after k rewards:

    A^(1)_t = -V(s_t) + r_t + gamma V(s_{t+1})
    A^(k)_t = -V(s_t) + r_t + gamma r_{t+1} + ... + gamma^k V(s_{t+k})

GAE (eq. 4) is their exponentially weighted average, which telescopes into a discounted sum of
one-step TD residuals:

    A^GAE_t = (1 - lam) (A^(1)_t + lam A^(2)_t + lam^2 A^(3)_t + ...)
            = sum_l (gamma lam)^l delta_{t+l},      delta_t = r_t + gamma V(s_{t+1}) - V(s_t)

lam = 0 gives the one-step estimate (low variance, biased by V); lam = 1 gives the Monte Carlo
return minus V (unbiased, high variance).

Episode ends need two different treatments, and mixing them up is a classic bug:

* **Termination** (the hopper fell): s_{t+1} is terminal, its value is 0 by definition, so the
  TD residual does not bootstrap: delta_t = r_t - V(s_t).
* **Truncation** (the time limit ran out; every FetchReach episode ends this way): the state
  s_{t+1} is an ordinary state that the agent would have continued from, so delta_t still
  bootstraps from V(s_{t+1}), where s_{t+1} is the *true final observation* of the episode
  (not the reset observation that a vector environment returns in its place).

In both cases the sum over l stops at the episode end: the next row of the buffer belongs to a
new episode.
"""

import torch


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    terminations: torch.Tensor,
    episode_ends: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> torch.Tensor:
    """Advantages A^GAE_t for a time-major batch collected by N parallel environments.

    Args:
        rewards: ``(T, N)``, r_t.
        values: ``(T, N)``, V(s_t).
        next_values: ``(T, N)``, V(s_{t+1}) of the true next state of step t: the final
            observation when the episode ended at step t, otherwise the following observation.
            For the last row it is the bootstrap value of the state the rollout stopped in.
        terminations: ``(T, N)``, 1 where s_{t+1} is terminal (no bootstrap), else 0.
        episode_ends: ``(T, N)``, 1 where the episode ended at step t, by termination *or*
            truncation (the recursion stops there), else 0.
        gamma: discount factor.
        gae_lambda: lam of eq. 4.

    Returns:
        ``(T, N)`` advantages. Returns (targets of V) are ``advantages + values``.
    """
    T = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(rewards[0])  # A_{t+1}, zero past the end of the rollout
    for t in reversed(range(T)):
        delta = (
            rewards[t] + gamma * (1.0 - terminations[t]) * next_values[t] - values[t]
        )  # TD residual
        last = delta + gamma * gae_lambda * (1.0 - episode_ends[t]) * last  # eq. 4, recursively
        advantages[t] = last
    return advantages
