"""ipg_her.py: the nu = 0 identity with PPO-KL, the off-policy term, replay, smoke, bad input;
ipg_her_recipe.py's recipe on top of it: the sigma rule, the action penalties, annealing."""

import copy
import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import (
    ScaledQ,
    assert_clean_error,
    assert_saved_policy_replays_last_evaluation,
    random_batch,
    run_dirs,
    run_script,
    scalars,
    smoke_run,
)
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from torch.distributions import Normal, kl_divergence
from toy_envs import counting_envs

import ipg_her
import ipg_her_recipe
import ppo_kl
from benchmarks import events
from common import diagnostics, replay
from common.her import HerReplayBuffer, sparse_return_range
from common.normalizer import InputNormalizer


def replay_of(states):
    """An ``ipg_update`` replay whose every batch holds ``states``."""
    return lambda n: itertools.repeat({"obs": states})


def test_nu_zero_without_cv_is_the_ppo_kl_update():
    torch.manual_seed(0)
    agent_ppo, agent_ipg = ppo_kl.Agent(5, 2), ppo_kl.Agent(5, 2)
    agent_ipg.load_state_dict(agent_ppo.state_dict())
    b = random_batch(200, 5, 2, agent_ppo)
    flags = dict(
        num_minibatches=4,
        update_epochs=3,
        learning_rate=3e-4,
        max_grad_norm=0.5,
        vf_coef=0.5,
        kl_target=0.01,
    )
    qf = ipg_her.QNetwork(5, 2, 32)
    replay = replay_of(torch.randn(16, 5))  # never called with nu = 0
    betas = []
    for agent, update in [
        (agent_ppo, lambda opt: ppo_kl.ppo_kl_update(agent_ppo, opt, b, 1.0, ppo_kl.Args(**flags))),
        (
            agent_ipg,
            lambda opt: ipg_her.ipg_update(
                agent_ipg,
                opt,
                b,
                1.0,
                ipg_her.Args(nu=0.0, use_cv=False, **flags),
                qf,
                replay,
            ),
        ),
    ]:
        optimizer = torch.optim.Adam(agent.parameters(), lr=3e-4, eps=1e-5, fused=True)
        torch.manual_seed(1)
        betas.append(update(optimizer)[0])
    assert betas[0] == betas[1]
    for key, value in agent_ppo.state_dict().items():
        torch.testing.assert_close(agent_ipg.state_dict()[key], value, rtol=0, atol=1e-7)


@pytest.mark.parametrize("module", [ipg_her, ipg_her_recipe], ids=lambda m: m.__name__)
def test_off_policy_term_moves_the_mean_up_the_critic(module):
    """nu = 1: the update is deterministic policy gradient ascent on Q_w(s, mu(s)) (eq. 7, 10)."""
    torch.manual_seed(0)
    agent = module.Agent(3, 2, 32)
    b = random_batch(64, 3, 2, agent)
    qf = module.QNetwork(3, 2, 32)
    states = torch.randn(256, 3)
    with torch.no_grad():
        before = qf(states, agent.actor_mean(states)).mean()
    args = module.Args(nu=1.0, num_minibatches=2, update_epochs=5, beta_init=0.0)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    module.ipg_update(agent, optimizer, b, 0.0, args, qf, replay_of(states))
    with torch.no_grad():
        after = qf(states, agent.actor_mean(states)).mean()
    assert after > before + 1e-3


@pytest.mark.parametrize("module", [ipg_her, ipg_her_recipe], ids=lambda m: m.__name__)
def test_kl_penalty_pulls_the_policy_back_to_pi_old(module):
    """Eq. 5's penalty beta KL[pi_old || pi], alone (nu = 1, no critic): one SGD step (lr 0.1, no
    clipping) from a policy that has moved away from pi_old is -0.1 beta grad KL, and the KL
    falls. At pi = pi_old its gradient is zero, so the policy is moved first."""
    torch.manual_seed(0)
    agent = module.Agent(5, 2, hidden=32)
    b = random_batch(64, 5, 2, agent)  # pi_old: the policy now
    with torch.no_grad():
        agent.actor_mean[-1].bias.add_(0.5)
        agent.actor_logstd.add_(0.3)
    params = agent.actor_parameters()

    def kl():
        return kl_divergence(Normal(b["mean"], b["std"]), agent.dist(b["obs"])).sum(-1).mean()

    grads = torch.autograd.grad(kl(), params, materialize_grads=True)
    expected = -0.1 * 2.0 * torch.cat([g.flatten() for g in grads])  # beta = 2
    before, kl_before = torch.cat([p.detach().flatten() for p in params]), kl().item()
    args = module.Args(nu=1.0, num_minibatches=1, update_epochs=1, vf_coef=0.0, max_grad_norm=1e9)
    module.ipg_update(agent, torch.optim.SGD(agent.parameters(), lr=0.1), b, 2.0, args)
    after = torch.cat([p.detach().flatten() for p in params])
    torch.testing.assert_close(after - before, expected)
    assert kl().item() < kl_before


@pytest.mark.parametrize("q_bar", ["mean", "sample"])
def test_at_nu_one_sigma_follows_only_the_kl_penalty_unless_q_bar_is_sampled(q_bar):
    """nu = 1 with Q_bar from the mean: nothing in eq. 10 reaches sigma but the KL penalty, whose
    gradient in log sigma, 1 - (sigma_old^2 + delta^2) / sigma^2 per dimension, is negative once
    the mean has moved by delta: each update can only widen sigma (Adam turns that small, steady
    gradient into steps of about the learning rate). This is the entropy climb of the FetchPush
    runs. With Q_bar sampled, the critic's gradient reaches sigma as well: on a critic concave in
    the action, E[Q(s, mu + sigma eps)] falls with sigma, and sigma narrows."""

    class Bowl(torch.nn.Module):  # Q(s, a) = -|a - 0.5|^2: the best action is 0.5
        def forward(self, s, a):
            return -((a - 0.5) ** 2).sum(-1)

    torch.manual_seed(0)
    agent, qf = ipg_her.Agent(3, 2, 32), Bowl()
    states = torch.randn(256, 3)
    args = ipg_her.Args(nu=1.0, q_bar=q_bar, num_minibatches=2, update_epochs=5)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    log_std = [agent.actor_logstd.detach().clone()]
    for seed in range(5):  # five updates, each from the policy the last one left
        b = random_batch(64, 3, 2, agent, seed)
        ipg_her.ipg_update(agent, optimizer, b, 1.0, args, qf, replay_of(states))
        log_std.append(agent.actor_logstd.detach().clone())
    steps = torch.diff(torch.cat(log_std), dim=0)
    assert (steps > 0).all() if q_bar == "mean" else (steps < 0).all()


@pytest.mark.parametrize(
    "script, env_id, flags",
    [
        ("ipg_her", "FetchReach-v4", ["--her"]),
        ("ipg_her", "FetchReach-v4", ["--no-her", "--nu", "0.5", "--use-cv", "--off-policy-states", "batch"]),
        ("ipg_her", "FetchPush-v4", []),  # the paper's algorithm on a hard task: it runs
        ("ipg_her_recipe", "Hopper-v5", ["--num-steps", "100", "--twin-critic", "--q-bar", "sample"]),
        ("ipg_her_recipe", "FetchPush-v4", []),  # the fetch suite's tasks (benchmarks/run.py),
        ("ipg_her_recipe", "FetchPickAndPlace-v4", []),  # each with its own defaults
        ("ipg_her_recipe", "FetchSlide-v4", []),
    ],
)
def test_smoke(tmp_path, script, env_id, flags):
    tiny = "--total-timesteps 400 --num-envs 2 --critic-steps 4 --update-epochs 2"
    tiny += " --eval-freq 200 --eval-episodes 2 --hidden 32 --save-model"
    run_dir, tags = smoke_run(f"{script}.py", tmp_path, env_id, *tiny.split(), *flags)
    expected = {
        "losses/critic_loss",
        "losses/q_values",
        "ipg/nu",
        "ipg/on_policy_term",
        "ipg/off_policy_term",
        "ipg/effective_nu",
        "ipg/grad_var",
        "ipg/grad_var_cv",
        "losses/beta",
        "losses/approx_kl",
        "charts/policy_entropy",
        "charts/SPS",
        "eval/episodic_return",
        "charts/episodic_return",
    }
    if env_id.startswith("Fetch"):
        expected |= {"charts/success_rate", "eval/success_rate"}
    assert expected <= set(tags), expected - set(tags)
    assert ("ipg/alpha" in tags) == (script == "ipg_her_recipe")  # the sigma rule's, the recipe's
    assert len(tags["losses/critic_loss"]) >= 2 and len(tags["eval/episodic_return"]) >= 2
    ckpt = torch.load(run_dir / "model.pt", weights_only=False)
    assert {"agent", "qf", "qf_target", "normalizer", "args", "format_version"} <= set(ckpt)
    assert_saved_policy_replays_last_evaluation(run_dir, env_id)


@pytest.mark.parametrize("script", ["ipg_her_recipe", "ipg_her"])
def test_anneal_lr_takes_the_learning_rates_linearly_to_zero(tmp_path, script):
    """--anneal-lr: at iteration i of N, lr = (1 - (i - 1) / N) lr_0 for the policy's Adam
    (charts/learning_rate); the recipe's anneals the critic's too (its state in resume.pt at the
    end), ipg_her.py's, as PPO's, the policy's alone."""
    flags = "--total-timesteps 400 --critic-steps 2 --update-epochs 1 --hidden 16 --eval-freq 0"
    flags += " --eval-episodes 1 --critic-learning-rate 2e-3 --resume-freq 400 --anneal-lr"
    flags = flags.split()
    run_dir, tags = smoke_run(f"{script}.py", tmp_path, "FetchSlide-v4", *flags)
    fracs = [1.0, 0.75, 0.5, 0.25]  # N = 400 / 100 = 4 iterations
    logged = [value for _, value in tags["charts/learning_rate"]]
    np.testing.assert_allclose(logged, [1e-3 * f for f in fracs], rtol=1e-6)
    resume = torch.load(run_dir / "resume.pt", weights_only=False)
    critic_frac = fracs[-1] if script == "ipg_her_recipe" else 1.0
    assert resume["q_optimizer"]["param_groups"][0]["lr"] == pytest.approx(2e-3 * critic_frac)


def test_replayed_transitions_never_cross_a_reset_and_keep_the_true_final_observation():

    torch.manual_seed(0)
    envs = counting_envs(2, goal=True)
    agent = ipg_her.Agent(4, 1, 16)
    with torch.no_grad():
        agent.actor_logstd.fill_(0.5)  # some episodes terminate early
    reward = lambda ag, g: -np.any(ag != g, axis=-1).astype(np.float32)
    rb = HerReplayBuffer(1000, 2, 2, 1, 2, reward, n_sampled_goal=0)
    raw_obs, _ = envs.reset(seed=0)
    norm = InputNormalizer(2, 2)
    ro, _, episodes = ipg_her.rollout(envs, agent, norm, raw_obs, 30, rb)
    n = rb.filled
    assert n == 30 and len(episodes) == int(ro["episode_ends"].sum()) > 0
    np.testing.assert_array_equal(rb.next_obs[:n], rb.obs[:n] + [0, 1])  # same episode, one step later
    np.testing.assert_array_equal(rb.next_achieved_goal[:n], rb.achieved_goal[:n] + [0, 1])
    np.testing.assert_array_equal(rb.desired_goal[:n, :, 0], rb.obs[:n, :, 0])
    ends = ro["episode_ends"].numpy().astype(bool)
    truncated = ends & ~ro["terminations"].numpy().astype(bool)
    assert truncated.any()
    assert np.all(rb.next_obs[:n][truncated][:, 1] == 5)  # the true final observation
    assert np.all(rb.obs[1:n][ends[:-1]][:, 1] == 0)  # the row after an end starts a new episode
    # the critic's replay holds the action executed (clipped to [-1, 1]), not the sampled one
    sampled = ro["actions"].numpy()
    assert np.any(np.abs(sampled) > 1), "no action outside the bounds: the check would be vacuous"
    np.testing.assert_array_equal(rb.actions[:n], np.clip(sampled, -1.0, 1.0))


def test_critic_targets_are_clipped_to_the_return_range():
    """With a target network that overestimates (Q' = 10), clipped targets are 0, the largest
    return of a 0/-1 reward."""
    torch.manual_seed(0)
    agent, qf = ipg_her.Agent(3, 2, 16), ipg_her.QNetwork(3, 2, 16)
    qf_target = ipg_her.QNetwork(3, 2, 16)
    torch.nn.init.zeros_(qf_target.net[-1].weight)
    torch.nn.init.constant_(qf_target.net[-1].bias, 10.0)
    d = {
        "obs": torch.randn(8, 3),
        "next_obs": torch.randn(8, 3),
        "actions": torch.randn(8, 2),
        "rewards": torch.zeros(8),
        "terminations": torch.zeros(8),
    }
    with torch.no_grad():
        q = qf(d["obs"], d["actions"])
    optimizer = torch.optim.SGD(qf.parameters(), lr=0.0)
    clipped, _ = ipg_her.critic_step(qf, qf_target, optimizer, agent, d, 0.98, 0.05, (-50.0, 0.0))
    assert abs(clipped - 0.5 * (q**2).mean().item()) < 1e-5
    raw, _ = ipg_her.critic_step(qf, qf_target, optimizer, agent, d, 0.98, 0.05)
    assert raw > clipped + 1.0


def policy_after_one_update(c, nu, use_cv, normalization, q_bar="sample"):
    """Actor parameters after one ``ipg_update`` on a fixed batch whose rewards (advantages,
    returns, critic) are scaled by c."""
    torch.manual_seed(0)
    agent, qf = ipg_her.Agent(5, 2, hidden=32), ipg_her.QNetwork(5, 2, 32)
    b = random_batch(128, 5, 2, agent)
    b = {**b, "advantages": c * b["advantages"], "returns": c * b["returns"]}
    q = ScaledQ(qf, c)
    if use_cv:
        b["cv"] = ipg_her.control_variate(q, agent, b["obs"], b["actions"])
    states = torch.randn(64, 5, generator=torch.Generator().manual_seed(3))
    args = ipg_her.Args(nu=nu, use_cv=use_cv, normalization=normalization, q_bar=q_bar, num_minibatches=2, update_epochs=2)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    torch.manual_seed(1)
    ipg_her.ipg_update(agent, optimizer, b, 1.0, args, q, replay_of(states))
    return torch.cat([p.detach().flatten() for p in agent.actor_parameters()])


@pytest.mark.parametrize("use_cv", [False, True])
@pytest.mark.parametrize("nu", [0.2, 0.5, 0.8])
def test_nu_means_eq_10_nu_whatever_the_reward_scale(nu, use_cv):
    """Rewards x 10 (so advantages, returns and Q_w x 10) leave the policy update unchanged with
    ``unbiased`` normalisation; with ``paper`` the off-policy term's weight grows with the scale."""
    base = policy_after_one_update(1.0, nu, use_cv, "unbiased")
    torch.testing.assert_close(policy_after_one_update(10.0, nu, use_cv, "unbiased"), base)
    paper = policy_after_one_update(1.0, nu, use_cv, "paper")
    assert not torch.allclose(policy_after_one_update(10.0, nu, use_cv, "paper"), paper)


@pytest.mark.parametrize("module", [ipg_her, ipg_her_recipe], ids=lambda m: m.__name__)
@pytest.mark.parametrize("use_cv", [False, True])
@pytest.mark.parametrize("nu", [0.2, 0.5, 0.8])
def test_update_direction_is_a_positive_multiple_of_eq_10(nu, use_cv, module):
    """One plain SGD step (lr 1, one minibatch, no KL, no clipping) moves the policy by exactly
    (1/sigma) [(1 - nu) g_on + b g_off], g_on the likelihood-ratio gradient of the centred
    signal, g_off the gradient of -Q_w(s, mu(s)), b = nu (or 1 with the control variate)."""
    torch.manual_seed(0)
    agent, qf = module.Agent(5, 2, hidden=32), module.QNetwork(5, 2, 32)
    b = random_batch(64, 5, 2, agent)
    b["advantages"] = 7.0 * b["advantages"]  # sigma far from 1
    if use_cv:
        b["cv"] = module.control_variate(qf, agent, b["obs"], b["actions"])
    raw = b["advantages"] - b["cv"] if use_cv else b["advantages"]
    sigma = raw.std()

    def grad(loss):
        grads = torch.autograd.grad(loss, agent.actor_parameters(), materialize_grads=True)
        return torch.cat([g.flatten() for g in grads])

    ratio = (agent.dist(b["obs"]).log_prob(b["actions"]).sum(-1) - b["logprobs"]).exp()
    g_on = grad(-(ratio * (raw - raw.mean())).mean())
    g_off = grad(-qf(b["obs"], agent.actor_mean(b["obs"])).mean())
    expected = ((1 - nu) * g_on + (1.0 if use_cv else nu) * g_off) / sigma

    recipe = {"action_l2": 0.0} if hasattr(module.Args, "action_l2") else {}  # eq. 10 alone: no action penalty
    args = module.Args(
        nu=nu,
        use_cv=use_cv,
        q_bar="mean",
        off_policy_states="batch",
        normalization="unbiased",
        num_minibatches=1,
        update_epochs=1,
        vf_coef=0.0,
        max_grad_norm=1e9,
        **recipe,
    )
    before = torch.cat([p.detach().flatten() for p in agent.actor_parameters()])
    module.ipg_update(agent, torch.optim.SGD(agent.parameters(), lr=1.0), b, 0.0, args, qf)
    after = torch.cat([p.detach().flatten() for p in agent.actor_parameters()])
    torch.testing.assert_close(before - after, expected, rtol=1e-4, atol=1e-6)


def test_replay_rewards_are_scaled_like_gae_rewards():
    """sample_replay multiplies the stored (raw) rewards by the reward scale GAE's rewards got."""
    batches = []
    for scale in (1.0, 0.25):
        rb = replay.ReplayBuffer(100, 1, 2, 1, seed=0)
        for t in range(10):
            rb.add(
                np.full((1, 2), t),
                np.zeros((1, 1)),
                np.array([t - 5.0]),
                np.full((1, 2), t + 1),
                np.zeros(1),
                np.array([t == 9]),
            )
        batches.append(replay.sample_replay(rb, InputNormalizer(2, 0), scale, 32)[0])
    torch.testing.assert_close(batches[1]["rewards"], 0.25 * batches[0]["rewards"])
    assert batches[0]["rewards"].abs().sum() > 0


def test_critic_targets_are_clipped_only_where_the_reward_is_fetchs_0_or_minus_1():
    """Fetch's reward (0 reached, -1 not) allows returns in [-1/(1-gamma), 0]; PointMaze's 0/+1
    reward would have its positive targets clipped to 0, silently: no range there."""
    reached = lambda ag, g: (np.linalg.norm(ag - g, axis=-1) < 0.05).astype(np.float32)
    fetch = lambda ag, g: reached(ag, g) - 1.0
    assert sparse_return_range(fetch, 3, 0.98) == pytest.approx((-50.0, 0.0))
    assert sparse_return_range(reached, 2, 0.98) is None


def diagnostics_run(seed: int = 0):
    """What ``interpolation_report`` reads of a ``Run``: the diagnostics' own random streams."""
    return SimpleNamespace(
        diagnostics_rng=np.random.default_rng(seed), diagnostics_generator=torch.Generator().manual_seed(seed)
    )


def interpolation(agent, qf, b, args, states, chunks=4):
    """``interpolation_report`` as ipg_her.py calls it, its replay always drawing ``states``."""
    return ipg_her.interpolation_report(agent, qf, b, args, lambda n, rng: [{"obs": states}], diagnostics_run(), chunks)


def test_gradient_diagnostics_measure_the_two_terms_and_the_control_variates_variance():
    """The norms of the update's two weighted terms, and effective nu = |off| / (|on| + |off|),
    against a hand computation at nu = 0.3; A_hat = A_bar + noise orthogonal to it with k times
    its norm has corr(A_hat, A_bar) = 1/sqrt(1 + k^2) exactly; with k = 0 (a right critic) the
    control variate removes the likelihood-ratio noise and the gradient variance falls."""
    torch.manual_seed(0)
    agent, qf = ipg_her.Agent(5, 2, hidden=16), ipg_her.QNetwork(5, 2, 16)
    b = random_batch(400, 5, 2, agent)
    cv = ipg_her.control_variate(qf, agent, b["obs"], b["actions"])
    centred = cv - cv.mean()
    states, params, args = torch.randn(64, 5), agent.actor_parameters(), ipg_her.Args(nu=0.3)
    for k in (0.0, 2.0):
        noise = torch.randn(400, generator=torch.Generator().manual_seed(1))
        noise -= noise.mean()
        noise -= (noise @ centred) / (centred @ centred) * centred  # orthogonal to A_bar
        b["advantages"] = cv + k * centred.norm() / noise.norm() * noise
        d = interpolation(agent, qf, b, args, states)  # A_bar: the critic's on the batch, cv
        assert d["corr_adv_cv"] == pytest.approx(1 / np.sqrt(1 + k**2), abs=1e-4)
        adv = b["advantages"]
        sigma = adv.std() + 1e-8
        ratio = (agent.dist(b["obs"]).log_prob(b["actions"]).sum(-1) - b["logprobs"]).exp()
        g_on = diagnostics.flat_grad(-(ratio * (adv - adv.mean()) / sigma).mean(), params)
        g_off = diagnostics.flat_grad(-qf(states, agent.actor_mean(states)).mean() / sigma, params)
        on, off = 0.7 * g_on.norm().item(), 0.3 * g_off.norm().item()
        assert d["on_grad_norm"] == pytest.approx(on, rel=1e-4)
        assert d["off_grad_norm"] == pytest.approx(off, rel=1e-4)
        assert d["effective_nu"] == pytest.approx(off / (on + off), rel=1e-4)
        assert np.isfinite(d["explained_variance"])
    b["advantages"] = cv
    d = interpolation(agent, qf, b, args, states, chunks=8)
    assert d["grad_var_cv"] < 0.5 * d["grad_var"]


def test_gradient_diagnostics_measure_the_update_that_will_run(monkeypatch):
    """The report's off-policy states are the update's: one draw of the replay, from the
    diagnostics' own stream (the training's never moves), or with --off-policy-states batch the
    batch's (no draw); its A_bar is the batch's cv with --use-cv, else the critic's on the
    batch, from the script's own ``control_variate``."""
    torch.manual_seed(0)
    agent, qf = ipg_her.Agent(5, 2, hidden=16), ipg_her.QNetwork(5, 2, 16)
    b = random_batch(64, 5, 2, agent)
    states, run, draws = torch.randn(32, 5), diagnostics_run(), []
    params = agent.actor_parameters()

    def replay_states(n, rng):
        draws.append((n, rng))
        return [{"obs": states}]

    def off_norm(s, nu=0.3):  # nu |g_off|, g_off on the states s, at the update's 1/sigma
        off_term = -qf(s, agent.actor_mean(s)).mean() / (b["advantages"].std() + 1e-8)
        return nu * diagnostics.flat_grad(off_term, params).norm().item()

    def measure(args):
        return ipg_her.interpolation_report(agent, qf, b, args, replay_states, run)

    d = measure(ipg_her.Args(nu=0.3))
    assert draws == [(1, run.diagnostics_rng)]
    assert d["off_grad_norm"] == pytest.approx(off_norm(states), rel=1e-4)
    d = measure(ipg_her.Args(nu=0.3, off_policy_states="batch"))
    assert len(draws) == 1  # no draw
    assert d["off_grad_norm"] == pytest.approx(off_norm(b["obs"]), rel=1e-4)
    assert off_norm(b["obs"]) != pytest.approx(off_norm(states), rel=1e-2)  # they differ
    critics = ipg_her.control_variate(qf, agent, b["obs"], b["actions"])
    d = measure(ipg_her.Args(nu=0.3))
    assert d["corr_adv_cv"] == pytest.approx(diagnostics.correlation(b["advantages"], critics))

    def unused(*_):
        raise AssertionError("with --use-cv the batch's cv is A_bar")

    b["cv"] = torch.randn(64, generator=torch.Generator().manual_seed(5))
    monkeypatch.setattr(ipg_her, "control_variate", unused)
    d = measure(ipg_her.Args(nu=0.3, use_cv=True))
    assert d["corr_adv_cv"] == pytest.approx(diagnostics.correlation(b["advantages"], b["cv"]))


def test_diagnostics_do_not_change_the_training(tmp_path):
    """The ipg/* diagnostics draw from a stream of their own: measured at every update or never,
    the same seed gives the same networks, bit for bit."""
    states = []
    for every in ("1", "0"):
        log_dir = tmp_path / every
        result = run_script(
            "ipg_her.py",
            log_dir,
            "--total-timesteps",
            "300",
            "--critic-steps",
            "4",
            "--update-epochs",
            "2",
            "--eval-episodes",
            "1",
            "--hidden",
            "16",
            "--nu",
            "0.5",
            "--q-bar",
            "sample",
            "--diagnostics-every",
            every,
            "--save-model",
        )
        assert result.returncode == 0, result.stderr
        (run_dir,) = run_dirs(log_dir)
        states.append(torch.load(run_dir / "model.pt", weights_only=False))
        assert ("ipg/effective_nu" in scalars(run_dir)) == (every == "1")
    for net in ("agent", "qf"):
        for key, value in states[0][net].items():
            assert torch.equal(value, states[1][net][key]), (net, key)


def test_resume_goes_on_deterministically_and_an_interrupted_stretch_is_not_logged_twice(
    tmp_path,
):
    """A run stopped at a resume point goes on from resume.pt into the same folder; from the same
    resume.pt the continuation is the same, bit for bit; events an interrupted run logged after
    its last resume point are dropped, so every step is logged once; other flags are refused."""
    flags = (
        "--total-timesteps",
        "200",
        "--critic-steps",
        "4",
        "--update-epochs",
        "2",
        "--eval-freq",
        "100",
        "--eval-episodes",
        "1",
        "--hidden",
        "16",
        "--nu",
        "0.5",
        "--resume-freq",
        "100",
        "--save-model",
    )
    result = run_script("ipg_her.py", tmp_path, *flags)
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(tmp_path)
    at_200 = (run_dir / "resume.pt").read_bytes()
    longer = [*flags[:1], "400", *flags[2:], "--resume", str(run_dir)]
    models = []
    for _ in range(2):  # the second time as if the first had died after logging to 400
        (run_dir / "resume.pt").write_bytes(at_200)
        result = run_script("ipg_her.py", tmp_path, *longer)
        assert result.returncode == 0, result.stderr
        assert run_dirs(tmp_path) == [run_dir]  # the same folder, no new one
        models.append(torch.load(run_dir / "model.pt", weights_only=False))
    for net in ("agent", "qf", "qf_target"):
        for key, value in models[0][net].items():
            assert torch.equal(value, models[1][net][key]), (net, key)
    tags = scalars(run_dir)
    assert [step for step, _ in tags["eval/success_rate"]] == [100, 200, 300, 400]
    critic_steps = [step for step, _ in tags["losses/critic_loss"]]
    assert critic_steps == sorted(set(critic_steps)) and critic_steps[-1] == 400
    resumed = torch.load(run_dir / "resume.pt", weights_only=False)
    assert resumed["global_step"] == 400 and resumed["rb"]["filled"] == 200  # 2 envs x 200 rows
    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    times = [e.wall_time for tag in acc.Tags()["scalars"] for e in acc.Scalars(tag)]
    assert events.read_run(run_dir)["wall_time"] < max(times) - min(times) - 1  # pauses left out
    result = run_script("ipg_her.py", tmp_path, *longer, "--nu", "0.8")
    assert_clean_error(result, "--nu 0.5", "now 0.8")


def test_the_control_variate_waits_for_the_critic(tmp_path):
    """Before the critic learns (learning_starts), the off-policy term that offsets A_bar is off,
    so A_bar must be off too: with --use-cv the run is the run without it, scalar for scalar (it
    subtracted an untrained critic's A_bar, uncompensated)."""
    flags = (
        "--seed",
        "2",
        "--total-timesteps",
        "1024",
        "--num-envs",
        "2",
        "--num-steps",
        "256",
        "--num-minibatches",
        "4",
        "--update-epochs",
        "2",
        "--nu",
        "0.5",
        "--learning-starts",
        "100000",
        "--eval-freq",
        "0",
        "--eval-episodes",
        "1",
        "--eval-workers",
        "0",
    )
    runs = []
    for extra in ((), ("--use-cv",)):
        _, tags = smoke_run("ipg_her.py", tmp_path / str(len(runs)), "Hopper-v5", *flags, *extra)
        runs.append({tag: v for tag, v in tags.items() if tag != "charts/SPS"})
    assert "losses/policy_loss" in runs[0] and "ipg/cv_mean" not in runs[1]
    assert runs[0] == runs[1]


def test_sigma_rule_is_one_step_of_dual_ascent_on_the_target_entropy():
    """ipg_her_recipe.py's sigma rule: alpha moves by 0.01 (H_target - H), H_target = act_dim *
    (log(2 pi e) / 2 + log sigma*); with a sigma* per dimension, each alpha_i by
    0.01 (H(N(0, sigma*_i^2)) - H(N(0, sigma_i^2)))."""
    h_target = 4 * (0.5 * np.log(2 * np.pi * np.e) + np.log(0.5))
    log_std = np.zeros(4)  # the summed rule reads only its length
    assert ipg_her_recipe.sigma_rule(0.3, h_target - 2.0, log_std, 0.5) == pytest.approx(0.3 + 0.02)
    assert ipg_her_recipe.sigma_rule(0.3, h_target + 5.0, log_std, 0.5) == pytest.approx(0.3 - 0.05)
    h = lambda std: 0.5 * np.log(2 * np.pi * np.e * np.square(std))  # noqa: E731  H(N(0, std^2))
    sigma, target, alpha = np.array([0.5, 2.0, 1.0]), (1.0, 1.0, 0.3), np.array([0.1, 0.2, 0.3])
    expected = alpha + 0.01 * (h(np.array(target)) - h(sigma))
    np.testing.assert_allclose(ipg_her_recipe.sigma_rule(alpha, 99.0, np.log(sigma), target), expected)


def sigma_rule_alone(act_dim: int, target_std, updates: int, start_std: float = 1.0):
    """The sigma rule with no critic and no KL penalty: ``updates`` updates of nu = 1 on random
    batches, each followed by the rule's step; each step's alpha and sigma per dimension."""
    torch.manual_seed(0)
    agent = ipg_her_recipe.Agent(3, act_dim, hidden=16, init_log_std=float(np.log(start_std)))
    optimizer = torch.optim.Adam(agent.parameters(), lr=0.05)
    args = ipg_her_recipe.Args(nu=1.0, target_std=target_std, num_minibatches=1, update_epochs=5)
    alpha, alphas, sigmas = 0.0, [], []
    for _ in range(updates):
        b = random_batch(32, 3, act_dim, agent)
        _, stats = ipg_her_recipe.ipg_update(agent, optimizer, b, 0.0, args, alpha=alpha)
        log_std = agent.actor_logstd.detach().numpy()[0]
        alpha = ipg_her_recipe.sigma_rule(alpha, stats["charts/policy_entropy"], log_std, target_std)
        alphas.append(alpha)
        sigmas.append(np.exp(log_std))
    return alphas, np.array(sigmas)


@pytest.mark.parametrize("start_std", [0.2, 5.0])
def test_sigma_rule_grows_sigma_below_the_target_and_shrinks_it_above(start_std):
    """The rule alone (no critic, no KL penalty): from below the target sigma grows, from above it
    shrinks (alpha turns negative, which SAC's one-sided rule cannot), and it ends near target."""
    alphas, sigmas = sigma_rule_alone(2, 1.0, 60, start_std)
    sigma = sigmas[-1].mean()
    assert (alphas[0] > 0) == (start_std < 1.0)  # the first step's sign: towards the target
    assert (sigma > start_std) == (start_std < 1.0)
    assert 0.5 < sigma < 2.0, sigma


def test_sigma_rule_per_dimension_moves_each_sigma_to_its_own_target():
    """One target per action dimension: from sigma 1 the rule alone grows the dimension aimed at
    2 and shrinks the one aimed at 0.3, each steadily until it reaches its target, and leaves the
    one aimed at 1; the summed rule moves all dimensions alike."""
    targets = (1.0, 2.0, 0.3)
    per_dim = sigma_rule_alone(3, targets, 40)[1]
    summed = sigma_rule_alone(3, float(np.exp(np.log(targets).mean())), 40)[1]  # the same H
    assert np.all(per_dim[:, 0] == 1.0)  # at its target from the start: alpha_0 stays 0
    for dim, reached in ((1, per_dim[:, 1] >= 2.0), (2, per_dim[:, 2] <= 0.3)):
        assert reached.any(), per_dim[:, dim]
        steps = np.diff(per_dim[: reached.argmax() + 1, dim])
        assert np.all(steps > 0) if dim == 1 else np.all(steps < 0), per_dim[:, dim]
    assert np.all(summed == summed[:, :1])  # one alpha: no dimension apart


def test_bounds_loss_adds_the_gradient_of_the_squared_excess_beyond_the_bounds():
    """One SGD step with the recipe's --bounds-loss 0.5 moves the policy by the step without it
    plus the gradient of 0.5 * mean((mu - clamp(mu, low, high))^2): mu(s) inside the bounds feels
    nothing, mu(s) beyond them is pulled back (rl_games' bounds loss, at the action bounds)."""
    torch.manual_seed(0)
    agent, states = ipg_her_recipe.Agent(5, 2, hidden=32), torch.randn(48, 5)
    with torch.no_grad():
        agent.actor_mean[-1].bias.copy_(torch.tensor([0.0, 1.0]))  # dim 1 at its upper bound
    qf = ipg_her_recipe.QNetwork(5, 2, 32, low=-1.0, high=1.0)
    mu = agent.actor_mean(states)
    assert (mu[:, 0].abs() < 1).all() and (mu[:, 1] > 1).any() and (mu[:, 1] < 1).any()
    b, steps = random_batch(64, 5, 2, agent), []
    for weight in (0.0, 0.5):
        a = copy.deepcopy(agent)
        args = ipg_her_recipe.Args(
            nu=1.0, bounds_loss=weight, num_minibatches=1, update_epochs=1, vf_coef=0.0, max_grad_norm=1e9
        )
        ipg_her_recipe.ipg_update(a, torch.optim.SGD(a.parameters(), lr=1.0), b, 0.0, args, qf, replay_of(states))
        steps.append(torch.cat([p.detach().flatten() for p in a.actor_parameters()]))
    beyond = (mu - 1.0).clamp(min=0.0)  # by hand: only dim 1 ever exceeds a bound
    grads = torch.autograd.grad(0.5 * beyond.pow(2).mean(), agent.actor_parameters(), materialize_grads=True)
    expected = torch.cat([g.flatten() for g in grads])
    assert expected.abs().max() > 1e-4  # the states beyond the bound pull
    torch.testing.assert_close(steps[0] - steps[1], expected)


def test_action_penalty_adds_the_gradient_of_l2_mean_mu_squared():
    """One SGD step (lr 1, no KL, no clipping) with the recipe's --action-l2 0.5 moves the policy
    by the step without it plus the gradient of 0.5 * mean(mu(s)^2) over the off-policy states."""
    torch.manual_seed(0)
    agent, qf = ipg_her_recipe.Agent(5, 2, hidden=32), ipg_her_recipe.QNetwork(5, 2, 32)
    b, states = random_batch(64, 5, 2, agent), torch.randn(48, 5)
    steps = []
    for l2 in (0.0, 0.5):
        a = ipg_her_recipe.Agent(5, 2, hidden=32)
        a.load_state_dict(agent.state_dict())
        args = ipg_her_recipe.Args(nu=1.0, action_l2=l2, num_minibatches=1, update_epochs=1, vf_coef=0.0, max_grad_norm=1e9)
        ipg_her_recipe.ipg_update(a, torch.optim.SGD(a.parameters(), lr=1.0), b, 0.0, args, qf, replay_of(states))
        steps.append(torch.cat([p.detach().flatten() for p in a.actor_parameters()]))
    grads = torch.autograd.grad(0.5 * agent.actor_mean(states).pow(2).mean(), agent.actor_parameters(), materialize_grads=True)
    torch.testing.assert_close(steps[0] - steps[1], torch.cat([g.flatten() for g in grads]))
