"""Gradient diagnostics: what an estimator does, measured on a batch, never moving the training.

Generic helpers: the scripts' own reports (``qprop_report`` in qprop_ppo.py,
``interpolation_report`` in ipg_her.py) pass the loss their update minimises, so a diagnostic
measures the update's own estimator, not a second copy of it. Random draws come from the
caller's ``generator`` (``Run.diagnostics_generator``).
"""

from collections.abc import Callable

import torch


def flat_grad(loss: torch.Tensor, params: list[torch.Tensor]) -> torch.Tensor:
    """d loss / d params as one vector (zeros for parameters the loss does not reach)."""
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return torch.cat([(torch.zeros_like(p) if g is None else g).flatten() for p, g in zip(params, grads, strict=True)])


def gradient_variances(losses: list[Callable], params, n: int, chunks: int, generator=None):
    """For each ``loss(rows)``: the trace of the covariance, over ``chunks`` disjoint random
    chunks of the ``n`` rows (the same chunks for every loss), of the chunk's gradient."""
    parts = torch.randperm(n, generator=generator).chunk(chunks)
    return [torch.stack([flat_grad(loss(rows), params) for rows in parts]).var(0).sum().item() for loss in losses]


def variance_report(agent, b: dict, cv: torch.Tensor, estimate: Callable, chunks: int, generator=None) -> dict:
    """Q-Prop's claim, measured on a batch ``b`` at theta = theta_old: ``grad_var`` and
    ``grad_var_cv``, the gradient variances of ``estimate(mb, False)`` and ``estimate(mb, True)``
    (a script's own loss on the minibatch ``mb`` of a chunk's rows, without and with the
    control variate A_bar = ``cv``: eq. 8 at eta = 0 and 1, the same expectation); the
    correlation ``corr_adv_cv`` of A_hat with A_bar; V's ``explained_variance``."""

    def loss(with_cv: bool):
        return lambda rows: estimate({k: v[rows] for k, v in b.items()} | {"cv": cv[rows]}, with_cv)

    params = agent.actor_parameters()
    var, var_cv = gradient_variances([loss(False), loss(True)], params, len(cv), chunks, generator)
    with torch.no_grad():
        values = agent.get_value(b["obs"])
    return {
        "grad_var": var,
        "grad_var_cv": var_cv,
        "corr_adv_cv": correlation(b["advantages"], cv),
        "explained_variance": explained_variance(values, b["returns"]),
    }


def correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    return torch.corrcoef(torch.stack([x, y]))[0, 1].item()


def explained_variance(values: torch.Tensor, returns: torch.Tensor) -> float:
    """1 - Var(R - V) / Var(R): how much of the returns' variance the baseline V explains."""
    return (1 - (returns - values).var() / (returns.var() + 1e-8)).item()
