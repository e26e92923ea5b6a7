"""benchmarks/step_rates.py: both sides' training rates recorded from their own logs, an output
folder that holds results refused, and a side that fails is one error line that leaves no
results."""

import json
import os
import subprocess
import sys

from conftest import ROOT, assert_clean_error

STUB = '''"""sb3_fetch.py as step_rates.py calls it: a summary with its rate, or a failure."""
import json, os, sys
argv = sys.argv
out = argv[argv.index("--out") + 1]
if os.environ.get("STUB_FAILS"):
    sys.exit("stub: failed")
os.makedirs(out, exist_ok=True)
summary = dict(train_steps_per_s=7.5, hyperparams=dict(batch_size="512"), argv=argv[1:])
open(os.path.join(out, "summary.json"), "w").write(json.dumps(summary))
'''


def step_rates(tmp_path, *flags, env=None):
    anchors = tmp_path / "anchors"
    anchors.mkdir(exist_ok=True)
    (anchors / "sb3_fetch.py").write_text(STUB)
    command = [sys.executable, "benchmarks/step_rates.py", "--anchor-python", sys.executable, "--anchors", str(anchors)]
    command += ["--tasks", "FetchPush-v4", "--steps", "200", "--out", str(tmp_path / "out"), *flags]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)


def test_each_rate_is_read_from_its_own_side(tmp_path):
    result = step_rates(tmp_path)
    assert result.returncode == 0, result.stderr
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    push = results["tasks"]["FetchPush-v4"]
    assert push["tqc_her"] == 7.5 and push["tqc_hyperparams"] == {"batch_size": "512"}
    assert push["ours"] > 7.5  # ours' charts/SPS at its last step, not the stub's
    argv = json.loads((tmp_path / "out" / "runs" / "tqc_her__FetchPush-v4" / "summary.json").read_text())["argv"]
    assert argv[:4] == ["--algo", "tqc_her", "--trained-agent", "--env-id"]
    table = (tmp_path / "out" / "table.md").read_text()
    assert f"| FetchPush-v4 | {push['ours']:.1f} | 7.5 | {push['ours'] / 7.5:.1f} |" in table


def test_an_output_folder_with_results_is_refused_and_kept(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "table.md").write_text("committed")
    assert_clean_error(step_rates(tmp_path), "holds results")
    assert (tmp_path / "out" / "table.md").read_text() == "committed"
    assert not (tmp_path / "out" / "runs").exists()


def test_a_side_that_fails_is_one_error_line_and_no_results(tmp_path):
    result = step_rates(tmp_path, env={**os.environ, "STUB_FAILS": "1"})
    assert_clean_error(result, "tqc_her__FetchPush-v4 failed")
    assert not (tmp_path / "out" / "results.json").exists() and not (tmp_path / "out" / "table.md").exists()
