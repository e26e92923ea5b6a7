"""Gradient diagnostics: what an estimator does, measured on a batch, never moving the training.

The scripts pass the loss functions their update minimises (Q-Prop's ``qprop_loss``, IPG's
``ipg_loss``), so a diagnostic measures the update's own estimator, not a second copy of it. Its
random draws come from the caller's ``generator`` (``Run.diagnostics_generator``).
"""

from collections.abc import Callable

import torch


def flat_grad(loss: torch.Tensor, params: list[torch.Tensor]) -> torch.Tensor:
    """d loss / d params as one vector (zeros for parameters the loss does not reach)."""
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return torch.cat([(torch.zeros_like(p) if g is None else g).flatten()
                      for p, g in zip(params, grads, strict=True)])  # fmt: skip


def gradient_variances(losses: list[Callable], params, n: int, chunks: int, generator=None):
    """For each ``loss(rows)``: the trace of the covariance, over ``chunks`` disjoint random
    chunks of the ``n`` rows (the same chunks for every loss), of the chunk's gradient."""
    parts = torch.randperm(n, generator=generator).chunk(chunks)
    return [torch.stack([flat_grad(loss(rows), params) for rows in parts]).var(0).sum().item()
            for loss in losses]  # fmt: skip


def correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    return torch.corrcoef(torch.stack([x, y]))[0, 1].item()


def explained_variance(values: torch.Tensor, returns: torch.Tensor) -> float:
    """1 - Var(R - V) / Var(R): how much of the returns' variance the baseline V explains."""
    return (1 - (returns - values).var() / (returns.var() + 1e-8)).item()
