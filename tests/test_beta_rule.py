"""The adaptive KL penalty's beta rule (the PPO paper, sec. 4), in every script that carries it,
through its own update: the update's mean KL d below d_targ / 1.5 halves beta, above
d_targ * 1.5 doubles it, in between leaves it, and beta stays in DPPO's bounds [1/35, 35]."""

import pytest
import torch
from conftest import random_batch

import ipg_her
import ipg_her_recipe
import ppo_kl
import qprop_ppo

UPDATES = {  # the update of each script, on the on-policy term alone (no critic)
    "ppo_kl": lambda agent, opt, b, beta, **kw: ppo_kl.ppo_kl_update(
        agent, opt, b, beta, ppo_kl.Args(num_minibatches=2, update_epochs=2, **kw)
    ),
    "qprop_ppo": lambda agent, opt, b, beta, **kw: qprop_ppo.qprop_update(
        agent, opt, b, beta, qprop_ppo.Args(num_minibatches=2, update_epochs=2, **kw)
    ),
    "ipg_her": lambda agent, opt, b, beta, **kw: ipg_her.ipg_update(
        agent, opt, b, beta, ipg_her.Args(nu=0.5, num_minibatches=2, update_epochs=2, **kw)
    ),
    "ipg_her_recipe": lambda agent, opt, b, beta, **kw: ipg_her_recipe.ipg_update(
        agent, opt, b, beta, ipg_her_recipe.Args(nu=0.5, num_minibatches=2, update_epochs=2, **kw)
    ),
}


def update(name: str, beta: float, kl_target: float) -> tuple[float, float]:
    """One update from the same agent, batch and seed: the new beta and the update's mean KL d."""
    torch.manual_seed(0)
    agent = ppo_kl.Agent(5, 2)
    b = random_batch(64, 5, 2, agent)
    optimizer = torch.optim.Adam(agent.parameters(), lr=3e-3)
    torch.manual_seed(1)
    new_beta, stats = UPDATES[name](agent, optimizer, b, beta, kl_target=kl_target)
    return new_beta, stats["losses/approx_kl"]


@pytest.mark.parametrize("name", UPDATES)
def test_beta_halves_doubles_or_stays_by_the_updates_kl(name):
    _, d = update(name, 1.0, 1.0)
    assert d > 0, "the update moved nothing: the rule's test would be vacuous"
    assert update(name, 1.0, 1.6 * d) == (0.5, d)  # d < d_targ / 1.5
    assert update(name, 1.0, d / 1.6) == (2.0, d)  # d > d_targ * 1.5
    assert update(name, 1.0, d * 1.4) == (1.0, d)  # in between: beta stays
    assert update(name, 1.0, d / 1.4) == (1.0, d)


@pytest.mark.parametrize("name", UPDATES)
def test_beta_stays_in_dppo_bounds(name):
    for beta, bound in ((1 / 35, 1 / 35), (1.5 / 35, 1 / 35), (35.0, 35.0), (20.0, 35.0)):
        _, d = update(name, beta, 1.0)  # the KL of an update depends on its beta
        kl_target = 10 * d if bound < 1 else d / 10  # halve towards the floor, double to the top
        assert update(name, beta, kl_target) == (pytest.approx(bound), d)
