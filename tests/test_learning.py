"""The learning check: IPG + HER must solve FetchReach-v4 within a short budget.

Budget and threshold come from measured seeds (see README, "Results"): with the defaults every
seed measured reached an evaluation success rate of 1.0 by 5,000 steps, while --no-her and
--nu 0 stayed at or below 0.15 there. The threshold 0.8 leaves a margin on both sides, so this
test fails if hindsight relabelling or the off-policy term breaks.
"""

import pytest

from conftest import run_dirs, run_script, scalars

BUDGET = ["--total-timesteps", "5000", "--eval-freq", "0", "--eval-episodes", "20"]
THRESHOLD = 0.8


@pytest.mark.parametrize("seed", ["1", "2"])
def test_ipg_her_learns_fetchreach(tmp_path, seed):
    result = run_script("ipg_her.py", tmp_path, "--env-id", "FetchReach-v4", "--seed", seed, *BUDGET, timeout=300)
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(tmp_path)
    success = scalars(run_dir)["eval/success_rate"][-1][1]
    assert success >= THRESHOLD, f"eval success {success} < {THRESHOLD} after 5,000 steps"
