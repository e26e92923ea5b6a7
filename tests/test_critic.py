"""critic_step of qprop_ppo.py, ipg_her.py and ipg_her_recipe.py (eq. 6-7): the TD target
r + gamma (1 - terminated) Q_w'(s', mu(s')), the gradient step on 0.5 E[(Q_w - target)^2], the
soft target update w' <- tau w + (1 - tau) w', IPG's clipping of the targets; the recipe's target
at a sampled a' ~ pi(s') and its twin critics (TD3)."""

import copy

import pytest
import torch

import ipg_her
import ipg_her_recipe
import qprop_ppo

OBS, ACT, HIDDEN = 3, 2, 16
GAMMA, TAU, LR = 0.9, 0.3, 0.1
MODULES = {"qprop_ppo": qprop_ppo, "ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}
IPG = {"ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}  # critic_step's target_range


def networks(module):
    """An agent, a critic and a target network that differs from it (own initialisation, outputs
    around 5), so that every term of the target matters."""
    torch.manual_seed(0)
    agent = module.Agent(OBS, ACT, 16)
    qf = module.QNetwork(OBS, ACT, HIDDEN)
    qf_target = module.QNetwork(OBS, ACT, HIDDEN)
    with torch.no_grad():
        qf_target.net[-1].bias.fill_(5.0)
        agent.actor_mean[-1].weight.mul_(100.0)  # mu(s') far from 0 and from the replay actions
    return agent, qf, qf_target


def replay_batch(n=12):
    g = torch.Generator().manual_seed(1)
    return {
        "obs": torch.randn(n, OBS, generator=g),
        "next_obs": torch.randn(n, OBS, generator=g),
        "actions": torch.randn(n, ACT, generator=g),
        "rewards": torch.randn(n, generator=g),
        "terminations": torch.tensor([1.0, 0.0, 0.0] * (n // 3)),  # a third terminated
    }


def hand_target(agent, qf_target, d, gamma=GAMMA, a_next=None):
    """r + gamma (1 - terminated) Q_w'(s', a'), row by row; a' = mu(s') unless given."""
    with torch.no_grad():
        mu_next = agent.actor_mean(d["next_obs"]) if a_next is None else a_next
        rows = []
        for i in range(len(d["rewards"])):
            if d["terminations"][i] == 1:
                rows.append(d["rewards"][i])  # no bootstrap past a termination
            else:
                q_next = qf_target(d["next_obs"][i : i + 1], mu_next[i : i + 1])[0]
                rows.append(d["rewards"][i] + gamma * q_next)
        return torch.stack(rows)


def flat(net):
    return torch.cat([p.detach().flatten() for p in net.parameters()])


def call(module, qf, qf_target, optimizer, agent, d, gamma=GAMMA, tau=TAU, target_range=None):
    extra = {} if target_range is None else {"target_range": target_range}
    return module.critic_step(qf, qf_target, optimizer, agent, d, gamma, tau, **extra)


def check_step(module, target_of, target_range=None):
    """One critic_step with SGD (lr 0.1): the loss and mean Q it returns, and the critic's new
    weights, are those of 0.5 E[(Q_w(s, a) - y)^2] for y = ``target_of(agent, qf_target, d)``."""
    agent, qf, qf_target = networks(module)
    d = replay_batch()
    y = target_of(agent, qf_target, d)
    twin = copy.deepcopy(qf)
    q = twin(d["obs"], d["actions"])
    loss = 0.5 * ((q - y) ** 2).mean()
    grads = torch.autograd.grad(loss, list(twin.parameters()))
    expected = flat(qf) - LR * torch.cat([g.flatten() for g in grads])
    optimizer = torch.optim.SGD(qf.parameters(), lr=LR)
    got_loss, got_mean_q = call(module, qf, qf_target, optimizer, agent, d, target_range=target_range)
    assert got_loss == pytest.approx(loss.item(), rel=1e-5)
    assert got_mean_q == pytest.approx(q.mean().item(), rel=1e-5)
    torch.testing.assert_close(flat(qf), expected)
    return agent, qf_target, d, y


@pytest.mark.parametrize("script", MODULES)
def test_td_target_does_not_bootstrap_past_a_termination(script):
    module = MODULES[script]
    agent, qf_target, d, y = check_step(module, hand_target)
    # not vacuous: bootstrapping at the terminated rows would give targets far from these
    with torch.no_grad():
        q_next = qf_target(d["next_obs"], agent.actor_mean(d["next_obs"]))
    done = d["terminations"] == 1
    assert torch.all((GAMMA * q_next[done]).abs() > 1.0)


@pytest.mark.parametrize("script", MODULES)
def test_soft_target_update_moves_the_target_a_fraction_tau_toward_the_new_critic(script):
    """w' <- tau w + (1 - tau) w' (eq. 6), w the critic's weights after its gradient step."""
    module = MODULES[script]
    agent, qf, qf_target = networks(module)
    d = replay_batch()
    target_before, critic_before = flat(qf_target), flat(qf)
    optimizer = torch.optim.SGD(qf.parameters(), lr=LR)
    call(module, qf, qf_target, optimizer, agent, d)
    critic_after = flat(qf)
    assert not torch.allclose(critic_after, critic_before), "the critic did not move"
    torch.testing.assert_close(flat(qf_target), TAU * critic_after + (1 - TAU) * target_before)
    # and the buffers (action bounds) are the critic's, untouched
    for b, b_target in zip(qf.buffers(), qf_target.buffers(), strict=True):
        assert torch.equal(b, b_target)


@pytest.mark.parametrize("script", IPG)
@pytest.mark.parametrize(
    "target_range",
    [(-0.5, 4.0), (1.0, 5.0)],
    ids=["clips-above-and-below", "lifts-every-terminated-row"],
)
def test_ipg_targets_are_clipped_to_target_range(script, target_range):
    """The clipped target clamp(r + gamma (1 - d) Q_w'(s', mu(s')), lo, hi), both bounds active
    on this batch, drives the step; the unclipped one would not."""

    def clipped(agent, qf_target, d):
        return hand_target(agent, qf_target, d).clamp(*target_range)

    _, _, _, y = check_step(IPG[script], clipped, target_range)
    agent, _, qf_target = networks(IPG[script])
    raw = hand_target(agent, qf_target, replay_batch())
    lo, hi = target_range
    inside = (raw > lo) & (raw < hi)
    assert (raw < lo).any() and (raw > hi).any() and inside.any(), "a bound never reached"
    assert not torch.allclose(y, raw)


def test_twin_critic_targets_the_smaller_target_q_and_steps_each_network_on_its_own_loss():
    """The recipe's TD3 clipped double Q (``--twin-critic``): y = r + gamma (1 - d)
    min(Q_1'(s', mu(s')), Q_2'(s', mu(s'))) row by row, by hand, and the step is SGD on
    0.5 E[(Q_1 - y)^2] + 0.5 E[(Q_2 - y)^2]; the second target network sits above the first on
    some rows and below on others, so neither head alone gives the target."""
    module = ipg_her_recipe
    torch.manual_seed(0)
    agent = module.Agent(OBS, ACT, 16)
    qf = module.QNetwork(OBS, ACT, HIDDEN, twin=True)
    qf_target = module.QNetwork(OBS, ACT, HIDDEN, twin=True)
    d = replay_batch()
    with torch.no_grad():
        mu_next = agent.actor_mean(d["next_obs"])
        q1n, q2n = qf_target(d["next_obs"], mu_next, both=True)
        qf_target.twin[0][-1].bias.add_((q1n - q2n).median())  # the two cross
        q1n, q2n = (n(torch.cat([d["next_obs"], mu_next], -1)).squeeze(-1) for n in (qf_target.net, qf_target.twin[0]))
        assert (q1n < q2n).any() and (q2n < q1n).any()
        rows = range(len(d["rewards"]))
        y = torch.stack([d["rewards"][i] + (1 - d["terminations"][i]) * GAMMA * torch.minimum(q1n[i], q2n[i]) for i in rows])
    copy_ = copy.deepcopy(qf)
    q1, q2 = copy_(d["obs"], d["actions"], both=True)
    loss = 0.5 * ((q1 - y) ** 2).mean() + 0.5 * ((q2 - y) ** 2).mean()
    grads = torch.autograd.grad(loss, list(copy_.parameters()))
    expected = flat(qf) - LR * torch.cat([g.flatten() for g in grads])
    optimizer = torch.optim.SGD(qf.parameters(), lr=LR)
    got_loss, got_mean_q = call(module, qf, qf_target, optimizer, agent, d)
    assert got_loss == pytest.approx(loss.item(), rel=1e-5)
    assert got_mean_q == pytest.approx(q1.mean().item(), rel=1e-5)  # the policy's critic
    torch.testing.assert_close(flat(qf), expected)


NET_NAMES = {"net.0.weight", "net.0.bias", "net.2.weight", "net.2.bias", "net.4.weight", "net.4.bias", "low", "high"}


@pytest.mark.parametrize("script", MODULES)
def test_one_critic_is_the_twin_critics_first_network_and_keeps_its_parameter_names(script):
    """One critic is the network it always was, in every script: the same parameters and names
    (checkpoints of earlier runs load); the recipe's twin critic starts with that network, and
    without --twin-critic it is that network alone, ``both=True`` giving its one Q."""
    module = MODULES[script]
    torch.manual_seed(0)
    one = module.QNetwork(OBS, ACT, HIDDEN)
    assert set(one.state_dict()) == NET_NAMES
    torch.manual_seed(0)
    recipes = ipg_her_recipe.QNetwork(OBS, ACT, HIDDEN)
    torch.manual_seed(0)
    two = ipg_her_recipe.QNetwork(OBS, ACT, HIDDEN, twin=True)
    assert set(recipes.state_dict()) == NET_NAMES and len(two.twin) == 1
    assert torch.equal(flat(one), flat(recipes)) and torch.equal(flat(one), flat(two.net))
    x, a = torch.randn(5, OBS), torch.randn(5, ACT)
    (q,) = recipes(x, a, both=True)
    assert torch.equal(q, one(x, a)) and torch.equal(one(x, a), two(x, a))
