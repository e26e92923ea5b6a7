"""ppo_kl.py: smoke runs on Hopper-v5 and FetchReach-v4, autoreset handling, seeding, bad input."""

import runpy
import sys

import gymnasium as gym
import pytest
import torch
from conftest import (
    ROOT,
    assert_saved_policy_replays_last_evaluation,
    run_dirs,
    run_script,
    scalars,
    smoke_run,
)
from toy_envs import counting_envs

import ppo_kl
from common.normalizer import RunningMeanStd

PPO_TAGS = {
    "charts/episodic_return",
    "charts/episodic_length",
    "charts/policy_entropy",
    "charts/SPS",
    "eval/episodic_return",
    "losses/policy_loss",
    "losses/value_loss",
    "losses/approx_kl",
    "losses/beta",
}


@pytest.mark.parametrize(
    "env_id, flags",
    [
        ("Hopper-v5", ["--num-envs", "2", "--num-steps", "128", "--total-timesteps", "768"]),
        ("FetchReach-v4", ["--num-envs", "2", "--num-steps", "50", "--total-timesteps", "200"]),
    ],
)
def test_smoke_logs_tags_and_saved_model_evaluates(tmp_path, env_id, flags):
    tiny = "--num-minibatches 4 --update-epochs 2 --eval-freq 100 --eval-episodes 2 --save-model"
    run_dir, tags = smoke_run("ppo_kl.py", tmp_path, env_id, *flags, *tiny.split())
    expected = PPO_TAGS | ({"charts/success_rate", "eval/success_rate"} if env_id.startswith("Fetch") else set())
    assert expected <= set(tags), expected - set(tags)
    assert len(tags["losses/beta"]) >= 2 and len(tags["eval/episodic_return"]) >= 2

    assert_saved_policy_replays_last_evaluation(run_dir, env_id)


def test_no_transition_crosses_a_reset_and_truncation_bootstraps_from_final_obs():
    torch.manual_seed(0)
    envs = counting_envs(3)
    agent = ppo_kl.Agent(2, 1)
    with torch.no_grad():
        agent.actor_logstd.fill_(0.5)  # wide enough that some episodes terminate early
    raw_obs, _ = envs.reset(seed=0)
    obs_rms = RunningMeanStd((2,))  # never updated: normalisation is the identity here
    ro, last_raw, episodes = ppo_kl.rollout(envs, agent, obs_rms, raw_obs, 40, update_norm=False)
    obs, final_obs, ends, terms = (
        ro["obs"],
        ro["final_obs"],
        ro["episode_ends"].bool(),
        ro["terminations"].bool(),
    )
    assert terms.any() and (ends & ~terms).any(), "the rollout should hold both kinds of episode end"
    assert len(episodes) == int(ends.sum())
    nxt = torch.cat([obs[1:], torch.as_tensor(last_raw, dtype=torch.float32)[None]])
    # within an episode the next row is the same episode one step later
    assert torch.equal(nxt[~ends][:, 0], obs[~ends][:, 0]) and torch.equal(nxt[~ends][:, 1], obs[~ends][:, 1] + 1)
    # where an episode ended, final_obs is its true last observation, the next row a new episode
    assert torch.equal(final_obs[ends][:, 0], obs[ends][:, 0]) and torch.equal(final_obs[ends][:, 1], obs[ends][:, 1] + 1)
    assert torch.all(nxt[ends][:, 1] == 0) and torch.all(nxt[ends][:, 0] != obs[ends][:, 0])
    assert torch.all(final_obs[ends & ~terms][:, 1] == 5)  # truncated by the time limit

    # bootstrap: with a known V, lam = 0 gives delta_t exactly, V(final_obs) after a truncation
    agent.get_value = lambda x: 10.0 * x[..., 1] + x[..., 0]
    gamma = 0.9
    b = ppo_kl.make_batch(agent, ro, torch.as_tensor(last_raw, dtype=torch.float32), gamma, 0.0)
    v = agent.get_value(obs)
    expected_next = torch.where(ends, agent.get_value(final_obs), agent.get_value(nxt))
    delta = ro["rewards"] + gamma * (~terms) * expected_next - v
    torch.testing.assert_close(b["advantages"], delta.flatten())
    trunc = (ends & ~terms).flatten()
    torch.testing.assert_close(
        b["advantages"][trunc],
        (1.0 + gamma * 50.0 + gamma * final_obs[ends & ~terms][:, 0] - v.flatten()[trunc]),
    )


def test_same_seed_same_run_another_seed_another_run(tmp_path):
    """Two runs with the same seed log the same value of every scalar at every step (all but the
    wall-clock charts/SPS) and save the same networks and normaliser, bit for bit, over three
    updates and two evaluations; a run with another seed differs in its logs and its weights."""
    flags = (
        "--env-id",
        "Hopper-v5",
        "--num-envs",
        "2",
        "--num-steps",
        "64",
        "--total-timesteps",
        "384",
        "--num-minibatches",
        "2",
        "--update-epochs",
        "2",
        "--eval-freq",
        "192",
        "--eval-episodes",
        "1",
        "--save-model",
    )
    runs = []
    for name, seed in (("a", "1"), ("b", "1"), ("c", "2")):
        result = run_script("ppo_kl.py", tmp_path / name, "--seed", seed, *flags)
        assert result.returncode == 0, result.stderr
        (run_dir,) = run_dirs(tmp_path / name)
        logged = {tag: v for tag, v in scalars(run_dir).items() if tag != "charts/SPS"}
        runs.append((logged, torch.load(run_dir / "model.pt", weights_only=False)))
    (logs, model), (same_logs, same_model), (other_logs, other_model) = runs
    assert len(logs["losses/policy_loss"]) == 3 and len(logs["eval/episodic_return"]) == 2
    assert same_logs == logs  # every tag, every step, every value
    parts = ("agent", "normalizer", "last_eval_seeds")
    leaves, same_leaves, other_leaves = (dict(flat_leaves({p: m[p] for p in parts})) for m in (model, same_model, other_model))
    assert leaves.keys() == same_leaves.keys() and len(leaves) > 13
    for key, value in leaves.items():
        assert torch.equal(torch.as_tensor(same_leaves[key]), torch.as_tensor(value)), key
    for tag in ("losses/policy_loss", "losses/value_loss", "eval/episodic_return"):
        assert other_logs[tag] != logs[tag], tag
    for key in ("agent.actor_mean.0.weight", "agent.critic.0.weight", "normalizer.mean.ndarray"):
        assert not torch.equal(other_leaves[key], leaves[key]), key


def flat_leaves(tree, prefix=""):
    """(dotted path, leaf) for every leaf of nested dicts (a model.pt's state dicts)."""
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from flat_leaves(value, f"{prefix}{key}.")
    else:
        yield prefix[:-1], tree


def test_an_interrupted_run_keeps_its_logs_saves_its_model_and_names_its_resume_point(tmp_path):
    """A run killed (SIGTERM) ends as Ctrl-C does, exit 143, logs and model kept, and says from
    which step --resume goes on: the last resume point (here 2,048, the step the killed run was
    resumed from), not the step it stopped at."""
    import os
    import signal
    import subprocess
    import time

    from conftest import ROOT, run_script

    same = ("--save-model", "--eval-episodes", "1", "--no-anneal-lr")  # resumed with the same
    result = run_script("ppo_kl.py", tmp_path, "--total-timesteps", "2048", "--resume-freq", "2048", *same)
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(tmp_path)
    cmd = [
        sys.executable,
        str(ROOT / "ppo_kl.py"),
        "--log-dir",
        str(tmp_path),
        "--total-timesteps",
        "1000000",
        "--resume-freq",
        "0",
        *same,
        "--resume",
        str(run_dir),
    ]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    deadline = time.time() + 120
    while proc.poll() is None and time.time() < deadline and scalars(run_dir)["losses/beta"][-1][0] <= 2048:
        time.sleep(1)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err  # 128 + SIGTERM, the shell convention
    assert "interrupted at step" in err and "\nstopped: " in out
    assert f"--resume {run_dir} goes on from step 2,048" in out.splitlines()[-1]  # the last line
    assert (run_dir / "model.pt").exists()
    assert scalars(run_dir)["losses/beta"][-1][0] > 2048


def reset_seeds(monkeypatch, tmp_path, seed: int) -> list[int]:
    """Every seed a tiny ppo_kl.py run passes to an environment's reset, in order: the two
    training envs first, then two evaluations of two episodes."""
    seen = []
    original = gym.Env.reset

    def recording_reset(self, *, seed=None, options=None):
        if seed is not None:
            seen.append(seed)
        return original(self, seed=seed, options=options)

    argv = [
        "ppo_kl.py",
        "--seed",
        str(seed),
        "--log-dir",
        str(tmp_path / str(seed)),
        "--num-envs",
        "2",
        "--num-steps",
        "64",
        "--total-timesteps",
        "256",
        "--num-minibatches",
        "2",
        "--update-epochs",
        "1",
        "--eval-freq",
        "128",
        "--eval-episodes",
        "2",
        "--eval-workers",
        "0",
    ]
    with monkeypatch.context() as patch, pytest.raises(SystemExit) as exit_info:
        patch.setattr(gym.Env, "reset", recording_reset)
        patch.setattr(sys, "argv", argv)
        runpy.run_path(str(ROOT / "ppo_kl.py"), run_name="__main__")
    assert exit_info.value.code == 0
    return seen


def test_runs_with_different_seeds_share_no_reset_seed(monkeypatch, tmp_path):
    """Seed 1's second env must not replay seed 2's first, nor an evaluation a training reset."""
    one, two = (reset_seeds(monkeypatch, tmp_path, s) for s in (1, 2))
    assert len(one) == len(two) == 2 + 2 * 2
    assert not set(one) & set(two)
    train, evaluations = one[:2], one[2:]
    assert not set(train) & set(evaluations)
    assert evaluations[:2] != evaluations[2:], "each evaluation plays new episodes"
    assert reset_seeds(monkeypatch, tmp_path / "again", 1) == one  # and the same seed repeats
