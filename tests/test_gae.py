"""GAE (eq. 4) against its definition: the explicit discounted sum of TD residuals."""

import torch

from common.gae import compute_gae


def explicit_gae(rewards, values, next_values, terminations, episode_ends, gamma, lam):
    """A_t = sum_{l >= 0} (gamma lam)^l delta_{t+l}, stopping after the episode's last step."""
    T, N = rewards.shape
    delta = rewards + gamma * (1 - terminations) * next_values - values
    adv = torch.zeros(T, N, dtype=torch.float64)
    for i in range(N):
        for t in range(T):
            for l in range(T - t):
                adv[t, i] += (gamma * lam) ** l * delta[t + l, i]
                if episode_ends[t + l, i]:
                    break
    return adv


def test_gae_matches_explicit_sum_with_terminations_and_truncations():
    g = torch.Generator().manual_seed(0)
    T, N, gamma, lam = 40, 3, 0.97, 0.9
    rewards, values, next_values = (
        torch.randn(T, N, generator=g, dtype=torch.float64) for _ in range(3)
    )
    ends = (torch.rand(T, N, generator=g) < 0.15).double()
    terminations = (
        ends * (torch.rand(T, N, generator=g) < 0.5).double()
    )  # the others are truncations
    assert terminations.sum() > 0 and (ends - terminations).sum() > 0
    adv = compute_gae(rewards, values, next_values, terminations, ends, gamma, lam)
    torch.testing.assert_close(
        adv, explicit_gae(rewards, values, next_values, terminations, ends, gamma, lam)
    )


def test_gae_lambda_limits():
    """lam = 0: the one-step TD residual; lam = 1 with no episode end: discounted return minus V."""
    g = torch.Generator().manual_seed(1)
    T, N, gamma = 10, 2, 0.9
    rewards, values, next_values = (
        torch.randn(T, N, generator=g, dtype=torch.float64) for _ in range(3)
    )
    zeros = torch.zeros(T, N, dtype=torch.float64)
    adv0 = compute_gae(rewards, values, next_values, zeros, zeros, gamma, 0.0)
    torch.testing.assert_close(adv0, rewards + gamma * next_values - values)
    # a consistent value sequence: next_values[t] = values[t + 1]
    next_values[:-1] = values[1:]
    adv1 = compute_gae(rewards, values, next_values, zeros, zeros, gamma, 1.0)
    discounts = gamma ** torch.arange(T, dtype=torch.float64)
    mc = sum(discounts[l] * rewards[l] for l in range(T)) + gamma**T * next_values[-1]
    torch.testing.assert_close(adv1[0], mc - values[0])
