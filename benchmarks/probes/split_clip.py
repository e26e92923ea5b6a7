"""Does the sigma rule's bonus throttle the policy mean's learning through the shared gradient clip?

    python benchmarks/probes/split_clip.py {record,split} ARGS OF ipg_her_recipe.py ...

``ipg_her_recipe.py`` clips the policy's gradient, the mean network's and log sigma's together, to
``--max-grad-norm``. The bonus -alpha H(pi) gives each of the d log sigma a gradient of -alpha (the
summed rule), a norm of |alpha| sqrt(d): with a large |alpha| the clip scales the mean network's
gradient down with it. ``record`` trains exactly as ``ipg_her_recipe.py`` does and prints at the
end how the clip scaled the policy's gradient (the factor's quantiles) and log sigma's share of the
norm; ``split`` clips the mean network and log sigma each on its own (V's clip is unchanged).
"""

import os
import runpy
import sys

import numpy as np
import torch

ROOT = os.path.abspath(os.path.join(__file__, "../../.."))  # the project root
original = torch.nn.utils.clip_grad_norm_
factors, sigma_shares = [], []


def is_policy(params: list) -> bool:
    """The policy's list ends with log sigma, shape (1, d); V's ends with a bias, shape (1,)."""
    return len(params) > 1 and params[-1].dim() == 2 and params[-1].shape[0] == 1


def clip_factor(mean_norm: float, sigma_norm: float, max_norm: float) -> tuple[float, float]:
    """The factor a joint clip scales each gradient by; log sigma's share of the squared norm."""
    total = float(np.hypot(mean_norm, sigma_norm))
    return min(1.0, max_norm / (total + 1e-6)), sigma_norm**2 / max(total**2, 1e-12)


def clip(split: bool):
    def clip_grad_norm_(parameters, max_norm, *args, **kwargs):
        params = list(parameters)
        if not is_policy(params):
            return original(params, max_norm, *args, **kwargs)
        norms = [0.0 if p.grad is None else p.grad.norm().item() for p in params]
        factor, share = clip_factor(float(np.linalg.norm(norms[:-1])), norms[-1], max_norm)
        factors.append(factor)
        sigma_shares.append(share)
        if split:  # each on its own: the bonus no longer scales the mean network's gradient
            original(params[-1:], max_norm, *args, **kwargs)
            return original(params[:-1], max_norm, *args, **kwargs)
        return original(params, max_norm, *args, **kwargs)

    return clip_grad_norm_


def summary() -> str:
    f, s = np.array(factors), np.array(sigma_shares)
    q = np.quantile(f, [0.05, 0.5, 0.95])
    return (
        f"policy clips: {len(f)}; the joint clip's factor: 5% {q[0]:.3g}, median {q[1]:.3g}, "
        f"95% {q[2]:.3g}; below 0.1 in {np.mean(f < 0.1):.0%}; log sigma's share of the "
        f"squared norm: median {np.median(s):.2f}"
    )


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in ("record", "split"):
        sys.exit("error: the first argument is record or split (then ipg_her_recipe.py's flags)")
    torch.nn.utils.clip_grad_norm_ = clip(split=sys.argv[1] == "split")
    sys.argv = [os.path.join(ROOT, "ipg_her_recipe.py"), *sys.argv[2:]]
    sys.path.insert(0, ROOT)
    try:
        runpy.run_path(sys.argv[0], run_name="__main__")
    finally:
        if factors:
            print(summary())
