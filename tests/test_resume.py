"""--resume is exact: a run stopped at a resume point and resumed equals the run that never
stopped, scalar for scalar (the environments go on mid-episode, every generator and statistic
as it was)."""

import pytest
from conftest import run_dirs, run_script, scalars

CASES = {
    # goal task: replay, hindsight relabelling, the critic; 25 steps of 50-step episodes a rollout
    "ipg_her": ("FetchReach-v4", ["--num-steps", "25", "--critic-steps", "4", "--hidden", "16",
                                  "--eval-freq", "150", "--eval-episodes", "2"], 150),
    # vector task: Hopper's episodes cross the resume point; reward scaling, the beta rule
    "ppo_kl": ("Hopper-v5", ["--num-steps", "64", "--num-minibatches", "2", "--update-epochs",
                             "2", "--no-anneal-lr", "--eval-freq", "256", "--eval-episodes",
                             "2"], 256),
}  # fmt: skip


@pytest.mark.parametrize("script", CASES)
def test_a_resumed_run_equals_the_run_that_never_stopped(tmp_path, script):
    env_id, flags, half = CASES[script]
    flags = [f"{script}.py", "--env-id", env_id, "--num-envs", "2", "--eval-workers", "0",
             "--resume-freq", str(half), *flags]  # fmt: skip
    runs = {}
    for name, budgets in (("whole", [2 * half]), ("resumed", [half, 2 * half])):
        log_dir = tmp_path / name
        for i, budget in enumerate(budgets):
            resume = ["--resume", str(run_dirs(log_dir)[0])] if i else []
            result = run_script(*flags[:1], log_dir, *flags[1:], "--total-timesteps",
                                str(budget), *resume)  # fmt: skip
            assert result.returncode == 0, result.stderr
        (run_dir,) = run_dirs(log_dir)
        runs[name] = {tag: v for tag, v in scalars(run_dir).items() if tag != "charts/SPS"}
    assert runs["whole"]["eval/episodic_return"][-1][0] == 2 * half
    assert runs["resumed"].keys() == runs["whole"].keys()
    for tag, values in runs["whole"].items():
        assert runs["resumed"][tag] == values, tag
