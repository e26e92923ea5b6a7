"""Three properties the published numbers rest on, each broken once to see its test fail: the
beta rule's 1.5 band (PPO's sec. 4), the recipe's grasped starts (ipg_her_recipe.py) reaching
PickAndPlace's training episodes, and its evaluations starting as the task does (never grasped)."""

import runpy
import sys

import numpy as np
import pytest
import torch
from conftest import ROOT, random_batch

import ipg_her
import ipg_her_recipe
import ppo_kl
from common import evaluate
from common.grasped_start import GraspedStart


def beta_after(module, kl_target: float, update) -> tuple[float, float]:
    """beta after one update from the same agent and batch (beta = 1 before it), and its KL."""
    torch.manual_seed(0)
    agent = module.Agent(5, 2)
    b = random_batch(64, 5, 2, agent)
    at_nu_0 = {"nu": 0.0} if module is not ppo_kl else {}  # IPG's on-policy end: PPO-KL's step
    args = module.Args(num_minibatches=2, update_epochs=2, kl_target=kl_target, **at_nu_0)
    optimizer = torch.optim.Adam(agent.parameters(), lr=3e-3)
    beta, stats = update(module)(agent, optimizer, b, 1.0, args)
    return beta, stats["losses/approx_kl"]


UPDATES = {"ppo_kl": lambda m: m.ppo_kl_update, "ipg_her": lambda m: m.ipg_update,
           "ipg_her_recipe": lambda m: m.ipg_update}  # fmt: skip


@pytest.mark.parametrize("name", UPDATES)
def test_beta_doubles_above_1_5_targets_and_halves_below_a_1_5th(name):
    """d = 1.7 d_targ doubles beta and d = d_targ / 1.7 halves it (a 2x band would leave both);
    d = 1.3 d_targ leaves it (a 1.2x band would not)."""
    module = {"ppo_kl": ppo_kl, "ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}[name]
    _, d = beta_after(module, 1e9, UPDATES[name])  # the update's KL does not depend on d_targ
    assert d > 0
    assert beta_after(module, d / 1.7, UPDATES[name])[0] == 2.0
    assert beta_after(module, d * 1.7, UPDATES[name])[0] == 0.5
    assert beta_after(module, d / 1.3, UPDATES[name])[0] == 1.0
    assert beta_after(module, d * 1.3, UPDATES[name])[0] == 1.0


def test_pick_and_place_trains_from_grasped_starts_and_evaluates_from_the_tasks_own(
    monkeypatch, tmp_path
):
    """ipg_her_recipe.py --grasped-start 1: every training episode starts with the object
    between the fingers (the flag reaches the training envs); every evaluation episode starts as
    the task does, the object apart on the table (the published success rates are the task's)."""
    train_gaps, eval_gaps, calls = [], [], [0]
    reset = GraspedStart.reset

    def recording_reset(self, **kwargs):
        obs, info = reset(self, **kwargs)
        train_gaps.append(np.linalg.norm(obs["observation"][6:9]))  # object minus gripper
        return obs, info

    policy_call = evaluate.Policy.__call__

    def recording_call(self, obs, stochastic=False):
        if calls[0] % 50 == 0:  # an episode's first step (50 steps each)
            eval_gaps.append(np.linalg.norm(obs["observation"][6:9]))
        calls[0] += 1
        return policy_call(self, obs, stochastic)

    argv = ["ipg_her_recipe.py", "--env-id", "FetchPickAndPlace-v4", "--grasped-start", "1.0",
            "--total-timesteps", "200", "--critic-steps", "2", "--eval-freq", "100",
            "--eval-episodes", "3", "--eval-workers", "0", "--log-dir", str(tmp_path)]  # fmt: skip
    monkeypatch.setattr(GraspedStart, "reset", recording_reset)
    monkeypatch.setattr(evaluate.Policy, "__call__", recording_call)
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(ROOT / "ipg_her_recipe.py"), run_name="__main__")
    assert done.value.code == 0
    assert len(train_gaps) >= 2 and max(train_gaps) < 0.02  # both envs' starts, grasped
    assert len(eval_gaps) == 6 and min(eval_gaps) > 0.05  # two evaluations of 3, on the table
