"""qprop_ppo.py: the control variate (eq. 9) and the estimator (eq. 8) against closed forms, the
eta-mode none = PPO-KL identity, smoke runs and bad input."""

import copy

import numpy as np
import pytest
import torch
import torch.nn as nn
from conftest import (
    ScaledQ,
    assert_saved_policy_replays_last_evaluation,
    random_batch,
    smoke_run,
)
from toy_envs import counting_envs

import ppo_kl
import qprop_ppo
from common.normalizer import RunningMeanStd


def test_eta_mode_none_update_equals_ppo_kl_update():
    torch.manual_seed(0)
    agent_ppo = ppo_kl.Agent(5, 2)
    agent_qprop = qprop_ppo.Agent(5, 2)
    agent_qprop.load_state_dict(agent_ppo.state_dict())
    b = random_batch(256, 5, 2, agent_ppo)
    flags = dict(num_minibatches=4, update_epochs=3)
    qf = qprop_ppo.QNetwork(5, 2)  # given, but unused with eta = 0
    results = []
    for agent, update, args in [
        (agent_ppo, ppo_kl.ppo_kl_update, ppo_kl.Args(**flags)),
        (
            agent_qprop,
            lambda *a: qprop_ppo.qprop_update(*a, qf=qf),
            qprop_ppo.Args(eta_mode="none", **flags),
        ),
    ]:
        optimizer = torch.optim.Adam(agent.parameters(), lr=3e-4, eps=1e-5, fused=True)
        torch.manual_seed(1)
        beta, _ = update(agent, optimizer, b, 1.0, args)
        results.append((beta, agent.state_dict()))
    assert results[0][0] == results[1][0]
    for key, value in results[0][1].items():
        torch.testing.assert_close(results[1][1][key], value, rtol=0, atol=1e-7)
    assert not torch.equal(results[0][1]["actor_logstd"], torch.zeros(1, 2)), "the update changed nothing"


def test_control_variate_has_zero_mean_under_the_policy():
    torch.manual_seed(0)
    agent, qf = qprop_ppo.Agent(3, 2), qprop_ppo.QNetwork(3, 2)
    with torch.no_grad():
        agent.actor_logstd.fill_(-0.3)
    states = torch.randn(4, 3).repeat_interleave(50_000, 0)
    with torch.no_grad():
        actions = agent.dist(states).sample()
    cv = qprop_ppo.control_variate(qf, agent, states, actions).reshape(4, -1)
    mean, se = cv.mean(1), cv.std(1) / np.sqrt(cv.shape[1])
    assert torch.all(cv.std(1) > 1e-3), "a degenerate control variate proves nothing"
    assert torch.all(mean.abs() < 4 * se), (mean, se)


class QuadraticQ(nn.Module):
    """Q(s, a) = -(a - k s)^2: a critic whose Taylor expansion at mu is not exact."""

    def __init__(self, k):
        super().__init__()
        self.k = k

    def forward(self, s, a):
        return -((a - self.k * s) ** 2).sum(-1)


def linear_gaussian_problem(theta0=0.3, theta1=0.5, sigma=0.7, k=1.5):
    """pi(a|s) = N(theta0 + theta1 s, sigma^2), s ~ N(0, 1), Q = -(a - k s)^2.

    J = E[Q] = -theta0^2 - (theta1 - k)^2 - sigma^2, so
    grad J = (-2 theta0, -2 (theta1 - k), -2 sigma^2) for (bias, weight, log sigma).
    """
    agent = qprop_ppo.Agent(1, 1)
    agent.actor_mean = nn.Linear(1, 1)
    with torch.no_grad():
        agent.actor_mean.bias.fill_(theta0)
        agent.actor_mean.weight.fill_(theta1)
        agent.actor_logstd.fill_(np.log(sigma))
    true_grad = torch.tensor([-2 * theta0, -2 * (theta1 - k), -2 * sigma**2])
    return agent, QuadraticQ(k), true_grad


def policy_gradient_estimates(agent, qf, eta_mode, batches=3000, n=32, seed=0):
    """Per-batch gradient estimates (bias, weight, log sigma) of J from qprop_loss, at
    theta = theta_old, with eta chosen by ``compute_eta`` as ``qprop_ppo.py`` chooses it."""
    g = torch.Generator().manual_seed(seed)
    estimates = []
    for _ in range(batches):
        s = torch.randn(n, 1, generator=g)
        with torch.no_grad():
            pi = agent.dist(s)
            a = pi.mean + pi.stddev * torch.randn(n, 1, generator=g)
            logprobs = pi.log_prob(a).sum(-1)
            value = -((pi.mean - qf.k * s) ** 2).sum(-1) - pi.stddev[:, 0] ** 2  # exact V(s) = E_a[Q(s, a)]
            adv = qf(s, a) - value  # A_hat, exact here
        cv = qprop_ppo.control_variate(qf, agent, s, a)
        eta = qprop_ppo.compute_eta(adv, cv, eta_mode)
        mb = {"obs": s, "actions": a, "logprobs": logprobs, "adv": adv - eta * cv, "eta": eta}
        loss = qprop_ppo.qprop_loss(agent, qf, agent.dist(s), mb)
        grads = torch.autograd.grad(-loss, [agent.actor_mean.bias, agent.actor_mean.weight, agent.actor_logstd])
        estimates.append(torch.stack([gr.sum() for gr in grads]))
    return torch.stack(estimates)


def test_qprop_estimator_is_unbiased_and_has_lower_variance_than_likelihood_ratio():
    agent, qf, true_grad = linear_gaussian_problem()
    qprop = policy_gradient_estimates(agent, qf, "ones")
    lr = policy_gradient_estimates(agent, qf, "none")
    for est in (qprop, lr):
        se = est.std(0) / np.sqrt(est.shape[0])
        assert torch.all((est.mean(0) - true_grad).abs() < 4 * se + 1e-6), (
            est.mean(0),
            true_grad,
            se,
        )
    # the control variate removes the first-order part of Q: less variance in the mean's parameters
    assert torch.all(qprop.var(0)[:2] < 0.75 * lr.var(0)[:2]), (qprop.var(0), lr.var(0))


@pytest.mark.parametrize(
    "eta_mode, unbiased",
    [
        ("batch-conservative", True),
        ("batch-aggressive", True),
        ("conservative", False),  # the paper's per-sample modes: eta_t depends on the action
        ("aggressive", False),
    ],
)
def test_which_eta_modes_are_unbiased(eta_mode, unbiased):
    """The docstring's claim, measured: one eta per batch keeps eq. 8 unbiased; eta_t chosen per
    sample from the sign of A_hat_t A_bar_t does not (its bias is many standard errors)."""
    agent, qf, true_grad = linear_gaussian_problem()
    est = policy_gradient_estimates(agent, qf, eta_mode)
    z = (est.mean(0) - true_grad) / (est.std(0) / np.sqrt(est.shape[0]))
    if unbiased:
        assert torch.all(z.abs() < 4), (eta_mode, z)
    else:
        assert torch.any(z.abs() > 6), (eta_mode, z)


def test_control_variate_is_the_first_order_taylor_term_of_the_critic():
    """A_bar = grad_a Q(s, a)|_{a = mu} . (a - mu) (eq. 9), against the closed form for
    Q = -(a - k s)^2, where grad_a Q at mu is -2 (mu - k s). (A zero mean alone would hold for
    any g . (a - mu).)"""
    agent, qf, _ = linear_gaussian_problem()
    s, a = torch.randn(64, 1), torch.randn(64, 1)
    with torch.no_grad():
        mu = agent.actor_mean(s)
    expected = (-2 * (mu - qf.k * s) * (a - mu)).sum(-1)
    torch.testing.assert_close(qprop_ppo.control_variate(qf, agent, s, a), expected)


@pytest.mark.parametrize("mistake", ["flipped sign", "no analytic term"])
def test_a_wrong_control_variate_or_missing_analytic_term_is_detected(monkeypatch, mistake):
    """The unbiasedness test has teeth: it fails for plausible mistakes in eq. 8 or 9."""
    agent, qf, true_grad = linear_gaussian_problem()
    if mistake == "flipped sign":
        correct = qprop_ppo.control_variate
        monkeypatch.setattr(qprop_ppo, "control_variate", lambda *a: -correct(*a))
    else:
        loss = qprop_ppo.qprop_loss

        def without_analytic_term(agent, qf, pi, mb, *a):
            return loss(agent, qf, pi, mb | {"eta": torch.zeros_like(mb["eta"])}, *a)

        monkeypatch.setattr(qprop_ppo, "qprop_loss", without_analytic_term)
    est = policy_gradient_estimates(agent, copy.deepcopy(qf), "ones", batches=1000)
    se = est.std(0) / np.sqrt(est.shape[0])
    assert torch.any((est.mean(0) - true_grad).abs() > 4 * se), mistake


@pytest.mark.parametrize(
    "eta",
    [torch.full((12,), -1.0), torch.tensor([1.0, 0.0, -1.0] * 4)],
    ids=["eta=-1", "eta per sample 1, 0, -1"],
)
def test_qprop_loss_weights_each_samples_analytic_term_by_its_eta(eta):
    """qprop_loss = -E[r_t A] - analytic_scale E[eta_t Q_w(s_t, mu(s_t))], value and gradient,
    against a hand computation (the Gaussian log-density written out, the analytic term summed
    sample by sample): eta = -1 flips the analytic term, eta_t = 0 drops sample t from it."""
    torch.manual_seed(0)
    n, scale = len(eta), 0.7
    agent, qf = qprop_ppo.Agent(3, 2), qprop_ppo.QNetwork(3, 2, 16)
    with torch.no_grad():
        qf.net[-1].bias.fill_(3.0)  # Q_w far from 0: the analytic term's sign shows in the value
    b = random_batch(n, 3, 2, agent)
    logprobs = b["logprobs"] + 0.2 * torch.randn(n, generator=torch.Generator().manual_seed(5))
    mb = {"obs": b["obs"], "actions": b["actions"], "logprobs": logprobs, "adv": b["advantages"], "eta": eta}
    params = agent.actor_parameters()

    def by_hand(eta):
        mu, log_std = agent.actor_mean(b["obs"]), agent.actor_logstd
        z = (b["actions"] - mu) / log_std.exp()
        logp = (-0.5 * z**2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)
        ratio = (logp - logprobs).exp()  # r_t(theta), not 1: theta != theta_old here
        analytic = sum(e * qf(b["obs"][i : i + 1], mu[i : i + 1])[0] for i, e in enumerate(eta))
        return -(ratio * b["advantages"]).mean() - scale * analytic / n

    loss = qprop_ppo.qprop_loss(agent, qf, agent.dist(b["obs"]), mb, scale)
    expected = by_hand(eta)
    torch.testing.assert_close(loss, expected)
    grad, expected_grad = (torch.cat([g.flatten() for g in torch.autograd.grad(x, params)]) for x in (loss, expected))
    torch.testing.assert_close(grad, expected_grad)
    # not vacuous: an analytic term weighted by 1 (eta ignored) is far from it
    unweighted = by_hand(torch.ones(n))
    assert (unweighted - expected).abs() > 1.0
    unweighted_grad = torch.cat([g.flatten() for g in torch.autograd.grad(unweighted, params)])
    assert not torch.allclose(unweighted_grad, expected_grad, rtol=0.1)


@pytest.mark.parametrize("normalization", ["paper", "unbiased"])
def test_normalization_modes(normalization):
    """One plain SGD step of qprop_update (lr 1, one minibatch, no KL, no clipping, no V) moves
    the policy by g_lr / sigma + c g_analytic, written out by hand: g_lr the likelihood-ratio
    gradient of the centred signal A_hat - eta A_bar, g_analytic that of -E[eta Q_w(s, mu(s))],
    sigma the signal's std. unbiased: c = 1 / sigma, the raw estimator divided by sigma; paper:
    c = 1, the analytic term not divided."""
    torch.manual_seed(0)
    agent, qf = qprop_ppo.Agent(3, 2), qprop_ppo.QNetwork(3, 2)
    b = random_batch(64, 3, 2, agent)
    b["advantages"] = 5.0 * b["advantages"]  # sigma far from 1, so the modes differ
    b["cv"] = qprop_ppo.control_variate(qf, agent, b["obs"], b["actions"])
    b["eta"] = qprop_ppo.compute_eta(b["advantages"], b["cv"], "ones")
    raw_signal = b["advantages"] - b["eta"] * b["cv"]
    sigma = raw_signal.std()
    params = agent.actor_parameters()

    def grad(loss):
        grads = torch.autograd.grad(loss, params, retain_graph=True, materialize_grads=True)
        return torch.cat([g.flatten() for g in grads])

    mu, log_std = agent.actor_mean(b["obs"]), agent.actor_logstd
    z = (b["actions"] - mu) / log_std.exp()
    logp = (-0.5 * z**2 - log_std - 0.5 * np.log(2 * np.pi)).sum(-1)  # the Gaussian, by hand
    ratio = (logp - b["logprobs"]).exp()
    g_lr = grad(-(ratio * (raw_signal - raw_signal.mean())).mean())
    g_analytic = grad(-(b["eta"] * qf(b["obs"], mu)).mean())
    assert g_lr.norm() > 0.1 * g_analytic.norm() > 0, "one term alone would not test the mix"
    unbiased, paper = (g_lr + g_analytic) / sigma, g_lr / sigma + g_analytic
    assert not torch.allclose(unbiased, paper, rtol=0.1)
    expected = unbiased if normalization == "unbiased" else paper

    args = qprop_ppo.Args(num_minibatches=1, update_epochs=1, normalization=normalization, max_grad_norm=1e9, vf_coef=0.0)
    before = torch.cat([p.detach().flatten() for p in params])
    qprop_ppo.qprop_update(agent, torch.optim.SGD(agent.parameters(), lr=1.0), b, 0.0, args, qf)
    after = torch.cat([p.detach().flatten() for p in agent.actor_parameters()])
    torch.testing.assert_close(before - after, expected, rtol=1e-3, atol=1e-5)


def test_eta_modes():
    adv, cv = torch.tensor([1.0, -2.0, 3.0, -1.0]), torch.tensor([2.0, -1.0, -1.0, 0.5])
    assert qprop_ppo.compute_eta(adv, cv, "conservative").tolist() == [1, 1, 0, 0]
    cov = qprop_ppo.batch_covariance(adv, cv)  # positive here
    assert cov > 0 and qprop_ppo.compute_eta(adv, cv, "batch-conservative").tolist() == [1] * 4
    assert qprop_ppo.compute_eta(adv, -cv, "batch-conservative").tolist() == [0] * 4
    assert qprop_ppo.compute_eta(adv, -cv, "batch-aggressive").tolist() == [-1] * 4
    assert qprop_ppo.compute_eta(adv, cv, "aggressive").tolist() == [1, 1, -1, -1]
    assert qprop_ppo.compute_eta(adv, cv, "ones").tolist() == [1, 1, 1, 1]
    assert qprop_ppo.compute_eta(adv, cv, "none").tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize(
    "env_id, flags",
    [
        ("Hopper-v5", ["--num-envs", "2", "--num-steps", "128", "--total-timesteps", "768"]),
        ("FetchReach-v4", ["--num-envs", "2", "--num-steps", "50", "--total-timesteps", "300"]),
    ],
)
def test_smoke_reaches_critic_and_qprop_updates(tmp_path, env_id, flags):
    tiny = "--num-minibatches 4 --update-epochs 2 --learning-starts 100 --critic-steps 8"
    tiny += " --eval-freq 100 --eval-episodes 1 --save-model"
    run_dir, tags = smoke_run("qprop_ppo.py", tmp_path, env_id, *flags, *tiny.split())
    expected = {
        "losses/critic_loss",
        "losses/q_values",
        "qprop/eta",
        "qprop/cov",
        "qprop/signal_std",
        "qprop/grad_var",
        "qprop/grad_var_cv",
        "qprop/corr_adv_cv",
        "losses/beta",
        "charts/episodic_return",
        "charts/policy_entropy",
        "charts/SPS",
        "eval/episodic_return",
    }
    assert expected <= set(tags), expected - set(tags)
    assert len(tags["qprop/eta"]) >= 2 and (run_dir / "model.pt").exists()
    assert_saved_policy_replays_last_evaluation(run_dir, env_id)


def policy_after_one_update(c, eta_mode, normalization):
    torch.manual_seed(0)
    agent, qf = qprop_ppo.Agent(5, 2), qprop_ppo.QNetwork(5, 2)
    b = random_batch(128, 5, 2, agent)
    b = {**b, "advantages": c * b["advantages"], "returns": c * b["returns"]}
    q = ScaledQ(qf, 20.0 * c)  # a critic large enough that the analytic term matters
    b["cv"] = qprop_ppo.control_variate(q, agent, b["obs"], b["actions"])
    b["eta"] = qprop_ppo.compute_eta(b["advantages"], b["cv"], eta_mode)
    args = qprop_ppo.Args(eta_mode=eta_mode, normalization=normalization, num_minibatches=2, update_epochs=2)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    torch.manual_seed(1)
    qprop_ppo.qprop_update(agent, optimizer, b, 1.0, args, q)
    return torch.cat([p.detach().flatten() for p in agent.actor_parameters()])


@pytest.mark.parametrize("eta_mode", ["batch-aggressive", "ones", "conservative"])
def test_update_is_the_same_whatever_the_reward_scale(eta_mode):
    """Rewards x 10 (advantages, returns, Q_w x 10) leave the policy update unchanged with
    ``unbiased`` normalisation (V's larger gradient is clipped apart from the policy's); with
    ``paper`` the analytic term's weight grows with the scale."""
    base = policy_after_one_update(1.0, eta_mode, "unbiased")
    torch.testing.assert_close(policy_after_one_update(10.0, eta_mode, "unbiased"), base)
    paper = policy_after_one_update(1.0, eta_mode, "paper")
    assert not torch.allclose(policy_after_one_update(10.0, eta_mode, "paper"), paper)


def test_replay_holds_the_executed_action():
    """The critic learns Q of the action the environment executed (clipped), while the rollout
    keeps the sampled one for the likelihood ratio and A_bar."""

    torch.manual_seed(0)
    envs = counting_envs(2)
    agent = qprop_ppo.Agent(2, 1)
    with torch.no_grad():
        agent.actor_logstd.fill_(0.5)
    rb = qprop_ppo.ReplayBuffer(1000, 2, 2, 1, seed=0)
    raw_obs, _ = envs.reset(seed=0)
    ro, _, _ = qprop_ppo.rollout(envs, agent, RunningMeanStd((2,)), raw_obs, 30, rb)
    sampled = ro["actions"].numpy()
    assert np.any(np.abs(sampled) > 1), "no action outside the bounds: the check would be vacuous"
    np.testing.assert_array_equal(rb.actions[:30], np.clip(sampled, -1.0, 1.0))
    torch.testing.assert_close(
        qprop_ppo.sample_replay(rb, RunningMeanStd((2,)), 0.5, 16)[0]["rewards"],
        torch.full((16,), 0.5),
    )


@pytest.mark.parametrize("sign, k", [(1.0, 0.0), (1.0, 1.0), (-1.0, 0.5)])
def test_qprop_report_falls_where_the_control_variate_is_right(sign, k):
    """A_hat = sign A_bar + noise, the noise centred, orthogonal to A_bar on the batch and k times
    its norm: corr(A_hat, A_bar) is then sign / sqrt(1 + k^2) exactly. Where A_hat is exactly
    A_bar (a right critic), the control variate takes the likelihood-ratio noise away: the chunk
    gradients' variance falls; where the critic has the sign wrong, eta = 1 adds variance."""
    torch.manual_seed(0)
    agent, qf = qprop_ppo.Agent(5, 2), qprop_ppo.QNetwork(5, 2, 16)
    b = random_batch(512, 5, 2, agent)
    b["cv"] = qprop_ppo.control_variate(qf, agent, b["obs"], b["actions"])
    cv = b["cv"] - b["cv"].mean()
    noise = torch.randn(512, generator=torch.Generator().manual_seed(7))
    noise = noise - noise.mean()
    noise = noise - (noise @ cv) / (cv @ cv) * cv
    noise = k * cv.norm() / noise.norm() * noise
    b["advantages"] = sign * b["cv"] + noise
    d = qprop_ppo.qprop_report(agent, qf, b)
    assert d["corr_adv_cv"] == pytest.approx(sign / np.sqrt(1 + k**2), abs=1e-4)
    if sign > 0 and k == 0:
        assert 0 <= d["grad_var_cv"] < 0.5 * d["grad_var"]
    elif sign < 0:
        assert d["grad_var_cv"] > 2 * d["grad_var"]


def test_qprop_report_leaves_the_training_stream_alone():
    """The diagnostics draw their chunks from their own generator: measuring does not move the
    global torch stream the training samples from (it did: turning them on changed training)."""
    torch.manual_seed(0)
    agent, qf = qprop_ppo.Agent(5, 2), qprop_ppo.QNetwork(5, 2, 16)
    b = random_batch(64, 5, 2, agent)
    b["cv"] = qprop_ppo.control_variate(qf, agent, b["obs"], b["actions"])
    state = torch.get_rng_state()
    qprop_ppo.qprop_report(agent, qf, b, torch.Generator().manual_seed(1))
    assert torch.equal(torch.get_rng_state(), state)
    qprop_ppo.qprop_report(agent, qf, b)  # without one: the global stream moves
    assert not torch.equal(torch.get_rng_state(), state)
