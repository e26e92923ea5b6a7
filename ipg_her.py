"""Interpolated Policy Gradient (paper eq. 10) on PPO-KL, with Hindsight Experience Replay (Figure 2).

Docs: README.md, section "IPG + HER". Papers: Gu et al. 2017, "Interpolated Policy Gradient";
Andrychowicz et al. 2017, "Hindsight Experience Replay"; Schulman et al. 2017 (PPO-KL).

IPG mixes an on-policy likelihood-ratio gradient with an off-policy one through a critic Q_w:

    grad J = (1 - nu) E_{rho^pi, pi}[ grad log pi(a|s) A_hat(s, a) ] + nu E_{s ~ beta}[ grad Q_bar_w(s) ]   (eq. 10)

with Q_bar_w(s) = E_{a ~ pi}[Q_w(s, a)], estimated by one reparameterised sample
Q_w(s, mu_theta(s) + sigma_theta eps) (``--q-bar sample``; its gradient is the deterministic
policy gradient of eq. 7 plus a gradient for sigma) or by Q_w(s, mu_theta(s)) (``--q-bar mean``).
The sample matters at nu near 1: the likelihood-ratio term is then the only other signal for
sigma, and the KL penalty alone inflates sigma whenever the mean moves (measured on FetchReach:
policy entropy rose from 5.7 to 9.3 over 30k steps with ``mean``, fell to about 1 with ``sample``). nu = 0 is PPO-KL, nu = 1 is DDPG with a stochastic
exploring policy. Here the on-policy part is PPO-KL's surrogate (eq. 5), so one minibatch loss is

    L = (1 - nu) * -E[r_t(theta) A_t] + nu * -E_{s ~ beta}[Q_w(s, mu_theta(s))] + beta_KL * KL[pi_old || pi_theta]

(the KL coefficient is called ``beta`` in the code, as in ``ppo_kl.py``; the state distribution
beta of the paper is ``--off-policy-states``: ``replay``, uniform over the replay buffer, as the
IPG paper found best, or ``batch``, the on-policy states). With ``--use-cv`` the learning signal
becomes A_hat - A_bar, A_bar the Taylor control variate of Q-Prop (eq. 9), and the off-policy
term's weight becomes 1 (IPG's b = 1).

Critic (eq. 6-7): Q_w(s, a) learns off-policy from the replay buffer with the target
r + gamma (1 - terminated) Q_w'(s', mu_theta(s')), using the current policy's mean at s' (no target
policy network), and a soft target update after every critic step (eq. 6). On goal tasks the
targets are clipped to [-1/(1-gamma), 0], the returns a 0/-1 reward allows (OpenAI baselines' HER
recipe): without it Q_w drifted above 0 and two of five seeds lost success late in training. The critic trains on
the new data *before* the policy update, so A_bar and the off-policy term use the updated critic.

HER (Figure 2) enters only through the off-policy parts: the critic learns from relabelled
transitions, and the off-policy term is evaluated at relabelled (state, goal) pairs. The
likelihood-ratio term keeps the real goals: a relabelled on-policy sample is not a sample of the
policy conditioned on the new goal, so using it would need importance weights (Rauber et al.
2019, "Hindsight Policy Gradients"); the off-policy terms need no such correction.

Inputs are normalised by running statistics, observation and goal separately. The replay buffer
stores raw observations and normalises them at sample time with the current statistics, so
stored data never goes stale when the statistics drift; the on-policy batch is normalised once,
when collected, since the policy must be updated on the inputs it acted on.
"""

import contextlib
import copy
import io
import os
import random
import re
import signal
import sys
import time
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.optim as optim
import tyro
from torch.distributions import Normal, kl_divergence
from torch.utils.tensorboard import SummaryWriter

from common.gae import compute_gae
from common.her import HerReplayBuffer
from common.normalizer import RunningMeanStd

with contextlib.redirect_stderr(io.StringIO()):  # its import prints a notice about Adroit tasks we never use
    import gymnasium_robotics
gym.register_envs(gymnasium_robotics)
torch.distributions.Distribution.set_default_validate_args(False)  # argument checks cost ~10% of a run


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment (part of the run folder's name)"""
    seed: int = 1
    """seed of python, numpy, torch and the environments"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    capture_video: bool = False
    """record the evaluation episodes as videos into the run folder (needs moviepy)"""
    save_model: bool = False
    """save the final weights and normaliser states into the run folder"""
    log_dir: str = "runs"
    """parent folder of the run folders"""
    eval_freq: int = 2500
    """evaluate the deterministic (mean) policy every this many environment steps (0: only at the end)"""
    eval_episodes: int = 20
    """episodes per evaluation"""
    torch_threads: int = 1
    """torch intra-op threads; one is fastest for these small networks (measured)"""

    # Algorithm specific arguments
    env_id: str = "FetchReach-v4"
    """the id of the gymnasium environment"""
    total_timesteps: int = 30_000
    """environment steps to train for, counted over all parallel envs"""
    num_envs: int = 2
    """the number of parallel environments"""
    num_steps: int = 50
    """steps per environment per rollout (batch = num_envs * num_steps)"""
    learning_rate: float = 1e-3
    """the learning rate of the policy and value networks (Adam)"""
    anneal_lr: bool = False
    """anneal the policy learning rate linearly to zero"""
    gamma: float = 0.98
    """the discount factor gamma"""
    gae_lambda: float = 0.95
    """lam of GAE (eq. 4)"""
    num_minibatches: int = 2
    """the number of on-policy minibatches per epoch"""
    update_epochs: int = 10
    """passes over the on-policy batch per update"""
    norm_adv: bool = True
    """normalise the learning signal of a batch to zero mean and unit std"""
    kl_target: float = 0.01
    """d_targ: the KL divergence per update the beta rule aims for"""
    beta_init: float = 1.0
    """initial KL penalty coefficient beta"""
    vf_coef: float = 0.5
    """coefficient of the value loss"""
    max_grad_norm: float = 0.5
    """the maximum norm for gradient clipping of the policy and value networks"""
    hidden: int = 128
    """width of the two hidden layers of every network"""
    norm_reward: bool = False
    """divide rewards by the running std of the discounted return (off: the critic and GAE must share one scale)"""

    # IPG arguments
    nu: float = 1.0
    """nu of eq. 10: weight of the off-policy term (0: PPO-KL, 1: DDPG-like with a stochastic policy)"""
    use_cv: bool = False
    """control variate: learning signal A_hat - A_bar (eq. 9) and off-policy weight 1"""
    off_policy_states: Literal["replay", "batch"] = "replay"
    """where the off-policy term's states come from: uniform from the replay buffer, or the on-policy batch"""
    q_bar: Literal["mean", "sample"] = "sample"
    """Q_bar_w(s) as Q_w(s, mu(s)) (mean) or Q_w(s, mu(s) + sigma eps), a reparameterised sample of E_pi[Q_w(s, a)]"""
    clip_q_target: bool = True
    """goal tasks: clip critic targets to the return range of the 0/-1 reward, [-1/(1-gamma), 0]"""
    off_policy_batch_size: int = 256
    """replay states per policy minibatch for the off-policy term"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    critic_learning_rate: float = 1e-3
    """the learning rate of the critic Q_w"""
    critic_batch_size: int = 256
    """transitions per critic step"""
    critic_steps: int = 20
    """critic steps per iteration"""
    tau: float = 0.05
    """soft target update rate of eq. 6 (after every critic step)"""
    learning_starts: int = 100
    """environment steps before the critic and the off-policy term start"""

    # HER arguments (goal tasks only)
    her: bool = True
    """relabel replayed transitions with hindsight goals (goal tasks; off on tasks without goals)"""
    her_n_sampled_goal: int = 4
    """k: relabelled transitions per real one (relabelled share 1 - 1/(k+1))"""
    her_goal_selection_strategy: Literal["future", "final", "episode"] = "future"
    """where relabelled goals come from: later in the episode, its end, or anywhere in it"""

    # to be filled in runtime
    batch_size: int = 0
    """the batch size (computed in runtime)"""
    minibatch_size: int = 0
    """the mini-batch size (computed in runtime)"""
    num_iterations: int = 0
    """the number of iterations (computed in runtime)"""


def fail(message: str) -> None:
    """Bad input: one clear line, no traceback, non-zero exit."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_args() -> Args:
    """``tyro.cli``, with a parse error reported as one line (tyro draws a box)."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(Args)
    except SystemExit as e:
        if e.code:
            fail(" ".join(re.sub(r"[│╭╮╰╯─]", " ", captured.getvalue()).split()))
        raise


def check_args(args: Args, argv: list[str]) -> None:
    if args.env_id not in gym.registry:
        fail(f"unknown --env-id {args.env_id!r}; use a registered gymnasium id such as FetchReach-v4 or Hopper-v5")
    for name in ("total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs", "eval_episodes",
                 "off_policy_batch_size", "buffer_size", "critic_batch_size"):  # fmt: skip
        if getattr(args, name) <= 0:
            fail(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.total_timesteps < args.batch_size:
        fail(f"--total-timesteps {args.total_timesteps} is less than one batch (num_envs * num_steps = {args.batch_size})")
    if args.batch_size % args.num_minibatches:
        fail(f"batch {args.batch_size} (num_envs * num_steps) does not split into {args.num_minibatches} minibatches; change --num-minibatches")
    if not 0.0 <= args.nu <= 1.0:
        fail(f"--nu must be in [0, 1], got {args.nu}")
    if not 0.0 < args.tau <= 1.0:
        fail(f"--tau must be in (0, 1], got {args.tau}")
    if args.critic_steps < 0 or args.her_n_sampled_goal < 0 or args.learning_starts < 0:
        fail("--critic-steps, --her-n-sampled-goal and --learning-starts must be non-negative")
    if args.capture_video:
        try:
            import moviepy  # noqa: F401

            env = gym.make(args.env_id, render_mode="rgb_array")
            env.reset(seed=0)
            env.render()
            env.close()
        except ImportError:
            fail("--capture-video needs moviepy: pip install moviepy")
        except Exception as e:
            fail(f"--capture-video: rendering {args.env_id} failed ({type(e).__name__}); MuJoCo needs an OpenGL backend, e.g. apt install libosmesa6 and MUJOCO_GL=osmesa")
    if not 0 < args.gamma <= 1 or not 0 <= args.gae_lambda <= 1:
        fail("--gamma must be in (0, 1] and --gae-lambda in [0, 1]")
    goal_task = isinstance(gym.spec(args.env_id).make().observation_space, gym.spaces.Dict)
    if not goal_task:
        her_flags = [a for a in argv if a.split("=")[0] in ("--her", "--her-n-sampled-goal", "--her-goal-selection-strategy")]
        if her_flags:
            fail(f"{her_flags[0].split('=')[0]} needs a goal task (Dict observation with desired_goal); {args.env_id} has none")
        args.her = False


def make_env(env_id: str, video_dir: str | None = None):
    def thunk():
        env = gym.make(env_id, render_mode="rgb_array" if video_dir else None)
        if video_dir:
            env = gym.wrappers.RecordVideo(env, video_dir, episode_trigger=lambda e: True, disable_logger=True)
        return gym.wrappers.RecordEpisodeStatistics(env)

    return thunk


class InputNormalizer:
    """Policy and critic input: normalised observation, followed on goal tasks by the normalised goal."""

    def __init__(self, obs_dim: int, goal_dim: int):
        self.obs_rms, self.goal_rms = RunningMeanStd((obs_dim,), clip=5.0), RunningMeanStd((goal_dim,), clip=5.0)
        self.goal_task = goal_dim > 0

    def update(self, raw) -> None:
        if self.goal_task:
            self.obs_rms.update(raw["observation"])
            self.goal_rms.update(np.concatenate([raw["desired_goal"], raw["achieved_goal"]]))
        else:
            self.obs_rms.update(raw)

    def __call__(self, obs: np.ndarray, goal: np.ndarray | None = None) -> torch.Tensor:
        x = self.obs_rms.normalize(obs)
        if self.goal_task:
            x = np.concatenate([x, self.goal_rms.normalize(goal)], axis=-1)
        return torch.as_tensor(x)

    def raw(self, raw) -> torch.Tensor:
        """Normalise a raw environment observation (a Dict on goal tasks)."""
        return self(raw["observation"], raw["desired_goal"]) if self.goal_task else self(raw)

    def state_dict(self) -> dict:
        return {"obs_rms": self.obs_rms.state_dict(), "goal_rms": self.goal_rms.state_dict()}


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """Gaussian policy pi_theta(a|s) = N(mu_theta(s), diag(exp(log_std))^2) and baseline V_phi(s)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 256):
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, 1), std=1.0),
        )  # fmt: skip
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, hidden)), nn.Tanh(),
            layer_init(nn.Linear(hidden, act_dim), std=0.01),
        )  # fmt: skip
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))  # state-independent log std

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def dist(self, x: torch.Tensor) -> Normal:
        mean = self.actor_mean(x)
        return Normal(mean, self.actor_logstd.expand_as(mean).exp())


class QNetwork(nn.Module):
    """Critic Q_w(s, a), trained off-policy (eq. 6-7)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(),
            nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 1),
        )  # fmt: skip

    def forward(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([x, a], -1)).squeeze(-1)


# ALGO LOGIC: rollout with the current policy, every transition also stored for replay
def collect_rollout(envs, agent: Agent, norm: InputNormalizer, rb: HerReplayBuffer, raw_obs, num_steps: int):
    """Step the vector env ``num_steps`` times with actions sampled from pi_theta.

    Returns ``(rollout, raw_obs, episodes)`` as in ``ppo_kl.collect_rollout``; every transition
    also goes into the replay buffer ``rb`` raw, with its true next observation.
    """
    T, N, act_dim = num_steps, envs.num_envs, envs.single_action_space.shape[0]
    low, high = envs.single_action_space.low, envs.single_action_space.high
    input_dim = norm.raw(raw_obs).shape[-1]
    ro = {"obs": torch.zeros((T, N, input_dim)), "final_obs": torch.zeros((T, N, input_dim)),
          "actions": torch.zeros((T, N, act_dim)), "rewards": torch.zeros((T, N)),
          "terminations": torch.zeros((T, N)), "episode_ends": torch.zeros((T, N))}  # fmt: skip
    episodes = []
    for t in range(T):
        norm.update(raw_obs)
        ro["obs"][t] = norm.raw(raw_obs)
        with torch.no_grad():
            ro["actions"][t] = agent.dist(ro["obs"][t]).sample()
        action = ro["actions"][t].numpy()
        next_raw, reward, terminated, truncated, infos = envs.step(np.clip(action, low, high))
        ended = terminated | truncated
        true_next = copy.deepcopy(next_raw)  # SAME_STEP autoreset: the reset obs replaced the final one
        for i in np.flatnonzero(ended):
            final = infos["final_obs"][i]
            if norm.goal_task:
                for key in true_next:
                    true_next[key][i] = final[key]
            else:
                true_next[i] = final
            ro["final_obs"][t, i] = norm.raw(final)
            info = infos["final_info"]
            success = float(info["is_success"][i]) if "is_success" in info else None
            episodes.append((t, i, float(info["episode"]["r"][i]), int(info["episode"]["l"][i]), success))
        if norm.goal_task:
            rb.add(raw_obs["observation"], action, reward, true_next["observation"], terminated, truncated,
                   raw_obs["achieved_goal"], true_next["achieved_goal"], raw_obs["desired_goal"])  # fmt: skip
        else:
            rb.add(raw_obs, action, reward, true_next, terminated, truncated)
        ro["rewards"][t] = torch.as_tensor(reward)
        ro["terminations"][t] = torch.as_tensor(terminated)
        ro["episode_ends"][t] = torch.as_tensor(ended)
        raw_obs = next_raw
    return ro, raw_obs, episodes


# ALGO LOGIC: advantages by GAE (eq. 3-4), bootstrapping through truncation
def make_batch(agent: Agent, ro: dict, last_obs: torch.Tensor, gamma: float, gae_lambda: float) -> dict:
    """GAE advantages and the pi_old statistics of a rollout, flattened (as in ``ppo_kl.make_batch``)."""
    with torch.no_grad():
        values = agent.get_value(ro["obs"])
        next_values = torch.cat([values[1:], agent.get_value(last_obs)[None]])
        next_values = torch.where(ro["episode_ends"].bool(), agent.get_value(ro["final_obs"]), next_values)
        advantages = compute_gae(ro["rewards"], values, next_values, ro["terminations"], ro["episode_ends"], gamma, gae_lambda)
        pi_old = agent.dist(ro["obs"])
        act_dim = ro["actions"].shape[-1]
        return {
            "obs": ro["obs"].flatten(0, 1),
            "actions": ro["actions"].flatten(0, 1),
            "logprobs": pi_old.log_prob(ro["actions"]).sum(-1).flatten(),
            "mean": pi_old.mean.reshape(-1, act_dim),
            "std": pi_old.stddev.reshape(-1, act_dim),
            "advantages": advantages.flatten(),
            "returns": (advantages + values).flatten(),
        }


def sample_replay(rb: HerReplayBuffer, norm: InputNormalizer, batch_size: int) -> dict:
    """A (hindsight-relabelled) replay batch, normalised with the current statistics."""
    s = rb.sample(batch_size)
    goal, next_goal = (s["desired_goal"], s["desired_goal"]) if norm.goal_task else (None, None)
    return {
        "obs": norm(s["obs"], goal), "next_obs": norm(s["next_obs"], next_goal),
        "actions": torch.as_tensor(s["action"]), "rewards": torch.as_tensor(s["reward"]),
        "terminations": torch.as_tensor(s["terminated"]),
    }  # fmt: skip


# ALGO LOGIC: the critic step (eq. 6-7)
def critic_step(qf: QNetwork, qf_target: QNetwork, q_optimizer: optim.Optimizer, agent: Agent, d: dict, gamma: float, tau: float,
                target_range: tuple[float, float] | None = None) -> tuple[float, float]:
    """One step of TD learning on a replay batch ``d``, then the soft target update of eq. 6.

    ``target_range`` clips the targets to the returns the rewards allow (OpenAI baselines' HER
    recipe): a critic that cannot overestimate keeps the off-policy term honest.
    """
    with torch.no_grad():
        next_q = qf_target(d["next_obs"], agent.actor_mean(d["next_obs"]))  # Q_w'(s', mu_theta(s'))
        target = d["rewards"] + gamma * (1.0 - d["terminations"]) * next_q
        if target_range is not None:
            target = target.clamp(*target_range)
    q = qf(d["obs"], d["actions"])
    loss = 0.5 * ((q - target) ** 2).mean()
    q_optimizer.zero_grad()
    loss.backward()
    q_optimizer.step()
    with torch.no_grad():
        for p, p_target in zip(qf.parameters(), qf_target.parameters()):
            p_target.lerp_(p, tau)  # theta' <- tau theta + (1 - tau) theta'   (eq. 6)
    return loss.item(), q.mean().item()


def control_variate(qf: QNetwork, agent: Agent, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """A_bar(s, a) = grad_a Q_w(s, a)|_{a = mu(s)} . (a - mu(s))   (eq. 9), no gradient to theta."""
    with torch.no_grad():
        mu = agent.actor_mean(obs)
    mu.requires_grad_(True)
    (grad_q,) = torch.autograd.grad(qf(obs, mu).sum(), mu)
    return (grad_q * (actions - mu)).sum(-1).detach()


# ALGO LOGIC: the IPG update (eq. 10) on the PPO-KL surrogate (eq. 5)
def ipg_update(agent: Agent, optimizer: optim.Optimizer, b: dict, beta: float, args: Args, qf: QNetwork | None = None, off_policy_states=None) -> tuple[float, dict]:
    """``update_epochs`` passes of minibatch Adam on the interpolated loss, then the beta rule.

    ``b`` is the on-policy batch (as in ``ppo_kl.ppo_kl_update``), with ``cv`` (A_bar) when
    ``args.use_cv``. ``off_policy_states(mb)`` returns the states of the off-policy term for
    the on-policy minibatch indices ``mb``. With nu = 0 and no control variate the update is
    exactly ``ppo_kl.ppo_kl_update``.
    """
    batch_size = b["obs"].shape[0]
    minibatch_size = batch_size // args.num_minibatches
    signal = b["advantages"] - b["cv"] if args.use_cv else b["advantages"]  # A_hat - A_bar, on the raw scale
    if args.norm_adv:
        signal = (signal - signal.mean()) / (signal.std() + 1e-8)
    off_weight = 1.0 if args.use_cv else args.nu  # b = 1 with the control variate
    use_off_policy = qf is not None and off_weight > 0
    pi_old = Normal(b["mean"], b["std"])
    on_term, off_term = torch.zeros(()), torch.zeros(())
    for epoch in range(args.update_epochs):
        perm = torch.randperm(batch_size)
        for start in range(0, batch_size, minibatch_size):
            mb = perm[start : start + minibatch_size]
            pi = agent.dist(b["obs"][mb])
            ratio = (pi.log_prob(b["actions"][mb]).sum(-1) - b["logprobs"][mb]).exp()  # r_t(theta)
            kl = kl_divergence(Normal(b["mean"][mb], b["std"][mb]), pi).sum(-1).mean()  # analytic Gaussian KL
            on_term = -(ratio * signal[mb]).mean()  # likelihood-ratio part, PPO's surrogate (eq. 5)
            pg_loss = (1.0 - args.nu) * on_term + beta * kl
            if use_off_policy:
                s_off = off_policy_states(mb)
                a_off = agent.actor_mean(s_off)
                if args.q_bar == "sample":  # a = mu + sigma eps: the gradient reaches sigma too
                    a_off = a_off + agent.actor_logstd.exp() * torch.randn_like(a_off)
                off_term = -qf(s_off, a_off).mean()  # -Q_bar_w(s), s ~ beta (eq. 10)
                pg_loss = pg_loss + off_weight * off_term
            v_loss = 0.5 * ((agent.get_value(b["obs"][mb]) - b["returns"][mb]) ** 2).mean()
            loss = pg_loss + args.vf_coef * v_loss
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
    with torch.no_grad():
        pi = agent.dist(b["obs"])
        d = kl_divergence(pi_old, pi).sum(-1).mean().item()  # d: mean KL[pi_old || pi_new] of the update
        entropy = pi.entropy().sum(-1).mean().item()
    stats = {"policy_loss": pg_loss.item(), "value_loss": v_loss.item(), "approx_kl": d, "beta": beta, "entropy": entropy,
             "on_policy_term": on_term.item(), "off_policy_term": off_term.item()}  # fmt: skip
    if d < args.kl_target / 1.5:  # the PPO paper's beta rule (sec. 4)
        beta /= 2
    elif d > args.kl_target * 1.5:
        beta *= 2
    return beta, stats


def evaluate(agent: Agent, norm: InputNormalizer, env_id: str, episodes: int, seed: int, video_dir: str | None = None):
    """Run the deterministic policy a = mu_theta(s) with frozen normaliser statistics.

    Returns the episodic returns and, on goal tasks, the successes (``is_success`` at the last step).
    """
    env = make_env(env_id, video_dir)()
    low, high = env.action_space.low, env.action_space.high
    returns, successes = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            with torch.no_grad():
                action = agent.actor_mean(norm.raw(obs)[None]).numpy()[0]
            obs, _, terminated, truncated, info = env.step(np.clip(action, low, high))
            done = terminated or truncated
        returns.append(info["episode"]["r"])
        if "is_success" in info:
            successes.append(info["is_success"])
    env.close()
    return np.array(returns, np.float64), np.array(successes, np.float64)


if __name__ == "__main__":
    args = parse_args()
    args.batch_size = args.num_envs * args.num_steps
    args.minibatch_size = args.batch_size // max(args.num_minibatches, 1)
    args.num_iterations = args.total_timesteps // max(args.batch_size, 1)
    check_args(args, sys.argv[1:])
    run_name = f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.join(args.log_dir, run_name)
    writer = SummaryWriter(run_dir)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill` ends a run cleanly, as Ctrl-C does
    writer.add_text(
        "hyperparameters",
        "|param|value|\n|-|-|\n%s" % ("\n".join([f"|{key}|{value}|" for key, value in vars(args).items()])),
    )

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.torch_threads)

    # env setup
    envs = gym.vector.SyncVectorEnv(
        [make_env(args.env_id) for _ in range(args.num_envs)], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert isinstance(envs.single_action_space, gym.spaces.Box), "only continuous action spaces are supported"
    space = envs.single_observation_space
    goal_task = isinstance(space, gym.spaces.Dict)
    obs_dim = space["observation"].shape[0] if goal_task else space.shape[0]
    goal_dim = space["desired_goal"].shape[0] if goal_task else 0
    act_dim = envs.single_action_space.shape[0]
    envs.single_action_space.seed(args.seed)

    norm = InputNormalizer(obs_dim, goal_dim)
    agent = Agent(obs_dim + goal_dim, act_dim, args.hidden)
    optimizer = optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)
    qf = QNetwork(obs_dim + goal_dim, act_dim, args.hidden)
    qf_target = copy.deepcopy(qf)
    q_optimizer = optim.Adam(qf.parameters(), lr=args.critic_learning_rate, fused=True)
    compute_reward = None
    if goal_task:
        reward_env = gym.make(args.env_id)  # gymnasium 1.x wrappers do not forward attributes: use .unwrapped
        compute_reward = lambda ag, g: reward_env.unwrapped.compute_reward(ag, g, None)  # noqa: E731
    rb = HerReplayBuffer(args.buffer_size, args.num_envs, obs_dim, act_dim, goal_dim, compute_reward,
                         args.her_n_sampled_goal if args.her else 0, args.her_goal_selection_strategy, seed=args.seed)  # fmt: skip
    ret_rms, running_return = RunningMeanStd(()), np.zeros(args.num_envs)  # for reward scaling
    beta = args.beta_init
    target_range = (-1.0 / (1.0 - args.gamma), 0.0) if goal_task and args.clip_q_target and not args.norm_reward else None

    global_step, train_time, last_eval, exit_code = 0, 0.0, 0, 0
    recent_success = []  # is_success of the last 100 training episodes (goal tasks)
    raw_obs, _ = envs.reset(seed=args.seed)
    try:
        for iteration in range(1, args.num_iterations + 1):
            t0 = time.time()
            if args.anneal_lr:
                optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / args.num_iterations) * args.learning_rate

            ro, raw_obs, episodes = collect_rollout(envs, agent, norm, rb, raw_obs, args.num_steps)
            for t, _, episodic_return, length, success in episodes:
                step = global_step + (t + 1) * args.num_envs
                writer.add_scalar("charts/episodic_return", episodic_return, step)
                writer.add_scalar("charts/episodic_length", length, step)
                if success is not None:
                    recent_success = (recent_success + [success])[-100:]
                    writer.add_scalar("charts/success_rate", np.mean(recent_success), step)
            global_step += args.batch_size
            if args.norm_reward:
                returns = np.zeros(ro["rewards"].shape)
                for t in range(args.num_steps):
                    running_return = running_return * args.gamma + ro["rewards"][t].numpy()
                    returns[t] = running_return
                    running_return[ro["episode_ends"][t].numpy() > 0] = 0.0
                ret_rms.update(returns.reshape(-1))
                ro["rewards"] = ro["rewards"] / float(np.sqrt(ret_rms.var + 1e-8))

            # ALGO LOGIC: critic first (eq. 6-7), so that A_bar and the off-policy term see the new data
            learning = global_step >= args.learning_starts and rb.num_sampleable() > 0
            if learning and args.critic_steps > 0:
                for _ in range(args.critic_steps):
                    d = sample_replay(rb, norm, args.critic_batch_size)
                    critic_loss, q_values = critic_step(qf, qf_target, q_optimizer, agent, d, args.gamma, args.tau, target_range)
                writer.add_scalar("losses/critic_loss", critic_loss, global_step)
                writer.add_scalar("losses/q_values", q_values, global_step)

            b = make_batch(agent, ro, norm.raw(raw_obs), args.gamma, args.gae_lambda)
            if args.use_cv:
                b["cv"] = control_variate(qf, agent, b["obs"], b["actions"])
            if args.off_policy_states == "replay":
                off_policy_states = lambda mb: sample_replay(rb, norm, args.off_policy_batch_size)["obs"]  # noqa: E731
            else:
                off_policy_states = lambda mb: b["obs"][mb]  # noqa: E731
            beta, stats = ipg_update(agent, optimizer, b, beta, args, qf if learning else None, off_policy_states)
            if not all(np.isfinite(v) for v in stats.values()):
                raise FloatingPointError(f"a loss became NaN or infinite at global step {global_step}: {stats}")
            train_time += time.time() - t0

            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/policy_entropy", stats["entropy"], global_step)
            writer.add_scalar("charts/SPS", int(global_step / train_time), global_step)
            for key in ("policy_loss", "value_loss", "approx_kl", "beta"):
                writer.add_scalar(f"losses/{key}", stats[key], global_step)
            writer.add_scalar("ipg/nu", args.nu, global_step)
            writer.add_scalar("ipg/on_policy_term", stats["on_policy_term"], global_step)
            writer.add_scalar("ipg/off_policy_term", stats["off_policy_term"], global_step)
            if args.use_cv:
                writer.add_scalar("ipg/cv_mean", b["cv"].mean().item(), global_step)

            if iteration == args.num_iterations or (args.eval_freq > 0 and global_step - last_eval >= args.eval_freq):
                last_eval = global_step
                video_dir = os.path.join(run_dir, "videos") if args.capture_video else None
                eval_returns, eval_success = evaluate(agent, norm, args.env_id, args.eval_episodes, args.seed + 10_000, video_dir)
                writer.add_scalar("eval/episodic_return", eval_returns.mean(), global_step)
                message = f"step={global_step} eval_return={eval_returns.mean():.1f}"
                if len(eval_success):
                    writer.add_scalar("eval/success_rate", eval_success.mean(), global_step)
                    message += f" eval_success={eval_success.mean():.2f}"
                print(f"{message} SPS={int(global_step / train_time)}", flush=True)
    except KeyboardInterrupt:
        print(f"interrupted at global step {global_step}; logs are kept in {run_dir}", file=sys.stderr)
        exit_code = 130
    except FloatingPointError as e:
        print(f"error: {e}", file=sys.stderr)
        exit_code = 1
    finally:
        if args.save_model:
            model_path = os.path.join(run_dir, "model.pt")
            torch.save({"agent": agent.state_dict(), "qf": qf.state_dict(), "normalizer": norm.state_dict(), "args": vars(args)}, model_path)
            print(f"model saved to {model_path}")
        envs.close()
        writer.close()
    sys.exit(exit_code)
