"""``--kl-early-stop`` (DPPO's early stop of an update's epochs), the same in all four scripts: an
update stops after the first epoch whose mean KL[pi_old || pi] exceeds ``kl_early_stop`` times
``kl_target``, and runs every epoch without it."""

import pytest
import torch
from conftest import random_batch

import ipg_her
import ipg_her_recipe
import ppo_kl
import qprop_ppo

UPDATES = {  # each script's update, on-policy only (no critic)
    ppo_kl: lambda agent, opt, b, args: ppo_kl.ppo_kl_update(agent, opt, b, 1.0, args),
    qprop_ppo: lambda agent, opt, b, args: qprop_ppo.qprop_update(agent, opt, b, 1.0, args, None),
    ipg_her: lambda agent, opt, b, args: ipg_her.ipg_update(agent, opt, b, 1.0, args),
    ipg_her_recipe: lambda agent, opt, b, args: ipg_her_recipe.ipg_update(agent, opt, b, 1.0, args),
}


def epochs_run(module, kl_early_stop) -> int:
    torch.manual_seed(0)
    agent = module.Agent(5, 2)
    b = random_batch(64, 5, 2, agent)
    flags = dict(update_epochs=6, num_minibatches=2, learning_rate=1e-2, kl_early_stop=kl_early_stop)
    if module in (ipg_her, ipg_her_recipe):
        flags |= dict(nu=0.0, use_cv=False)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-2)
    _, stats = UPDATES[module](agent, optimizer, b, module.Args(**flags))
    return stats["losses/epochs"]


@pytest.mark.parametrize("module", list(UPDATES), ids=lambda m: m.__name__)
def test_kl_early_stop_ends_the_epochs_once_the_kl_is_past_its_bound(module):
    assert epochs_run(module, None) == 6
    assert epochs_run(module, 1e-6) == 1  # any step is past 1e-6 x kl_target
    assert epochs_run(module, 1e6) == 6
