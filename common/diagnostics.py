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


def variance_report(agent, b: dict, cv: torch.Tensor, estimate: Callable, chunks: int,
                    generator=None) -> dict:  # fmt: skip
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
    return {"grad_var": var, "grad_var_cv": var_cv, "corr_adv_cv": correlation(b["advantages"], cv),
            "explained_variance": explained_variance(values, b["returns"])}  # fmt: skip


def correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    return torch.corrcoef(torch.stack([x, y]))[0, 1].item()


def explained_variance(values: torch.Tensor, returns: torch.Tensor) -> float:
    """1 - Var(R - V) / Var(R): how much of the returns' variance the baseline V explains."""
    return (1 - (returns - values).var() / (returns.var() + 1e-8)).item()


def interpolation_report(
    agent,
    qf,
    b: dict,
    args,
    replay: Callable,
    run,
    control_variate: Callable,
    ipg_loss: Callable,
    learning_signal: Callable,
    chunks=4,
) -> dict:
    """IPG's update measured on its batch ``b`` before it runs (theta = theta_old), through the
    script's own ``control_variate``, ``ipg_loss`` and ``learning_signal`` (its normalisation and
    weights): the norms of the two weighted terms of the policy gradient, (1 - nu) g_on and
    b g_off, and ``effective_nu`` = |off| / (|on| + |off|), the share the off-policy term really
    has; then ``variance_report`` with eq. 8 at eta = 0 and 1 (raw advantage scale, Q_bar from
    the mean). The off-policy states: the batch's, or one draw of ``replay(1, rng)``; random
    draws from ``run``'s diagnostics streams."""
    generator = run.diagnostics_generator
    cv = b["cv"] if args.use_cv else control_variate(qf, agent, b["obs"], b["actions"])
    off_states = b["obs"] if args.off_policy_states == "batch" else replay(
        1, run.diagnostics_rng)[0]["obs"]  # fmt: skip
    params = agent.actor_parameters()
    signal, _, off_weight, off_scale = learning_signal(b, args)  # the update's own
    on_term, off_term = ipg_loss(agent, qf, agent.dist(b["obs"]), b, signal, off_states,
                                 args.q_bar, generator)  # fmt: skip
    on = (1.0 - args.nu) * flat_grad(on_term, params).norm().item()
    off = off_weight * flat_grad(off_term * off_scale, params).norm().item()

    def estimate(mb: dict, with_cv: bool):  # eq. 8 at eta = 1 or 0, on the raw scale
        adv = mb["advantages"] - mb["cv"] if with_cv else mb["advantages"]
        on_term, off_term = ipg_loss(agent, qf, agent.dist(mb["obs"]), mb, adv,
                                     mb["obs"] if with_cv else None)  # fmt: skip
        return on_term + off_term

    measured = {"on_grad_norm": on, "off_grad_norm": off, "effective_nu": off / (on + off + 1e-12)}
    return measured | variance_report(agent, b, cv, estimate, chunks, generator)


def qprop_report(agent, qf, b: dict, qprop_loss: Callable, generator=None, chunks: int = 8):
    """Q-Prop's claim (``variance_report``) through the script's own ``qprop_loss``, on its
    batch ``b`` (with ``cv`` = A_bar) before the update."""

    def estimate(mb: dict, with_cv: bool):  # eq. 8 at eta = 1 or 0, on the raw scale
        eta = torch.full_like(mb["cv"], float(with_cv))
        mb |= {"adv": mb["advantages"] - eta * mb["cv"], "eta": eta}
        return qprop_loss(agent, qf, agent.dist(mb["obs"]), mb)

    return variance_report(agent, b, b["cv"], estimate, chunks, generator)
