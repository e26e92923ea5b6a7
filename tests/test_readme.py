"""The README is the product's first minute: its set-up line and test command are the ones CI
runs, every file it links exists, every script it shows a command of takes that command's flags
as given, and the main job runs what its paragraph says."""

import re
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def bash_blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", README, flags=re.DOTALL)


def test_the_set_up_line_and_the_test_command_are_the_ones_ci_runs():
    ci = (ROOT / ".ci" / "run").read_text()
    setup, test = bash_blocks()[0].strip(), next(b for b in bash_blocks() if "pytest" in b).strip()
    assert setup in ci, f"CI does not run the README's set-up line: {setup}"
    assert ci.strip().splitlines()[-1] == test, "CI's last line must be the README's test command"


def test_every_linked_file_exists():
    links = re.findall(r"\]\(([^)#]+?)(?:#[^)]*)?\)", README)
    local = [link for link in links if "://" not in link]
    assert len(local) >= 10, local
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"the README links files that do not exist: {missing}"


COMMANDS = [
    line.split("#")[0].strip()
    for block in bash_blocks()
    for line in block.splitlines()
    if line.startswith("python ") and line.split()[1].endswith(".py")
]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_script_command_parses(capsys, command):
    """The flags of each ``python script.py ...`` line are the script's: parsed and checked as
    its ``__main__`` does, nothing run, none refused, and each one's field holds what it gives."""
    script, *argv = shlex.split(command)[1:]
    args = parsed(capsys, script, argv)
    for flag, value in zip(argv, [*argv[1:], "--"], strict=True):
        if not flag.startswith("--"):  # a flag's value
            continue
        name = flag.removeprefix("--").replace("-", "_")
        if value.startswith("--"):  # a switch: --save-model, --no-her
            negated = not hasattr(args, name)
            assert getattr(args, name.removeprefix("no_") if negated else name) is not negated
        else:
            field = getattr(args, name)
            assert field == type(field)(value), f"{flag} {value} parsed as {field!r}"


def test_the_main_job_runs_what_its_paragraph_says(capsys):
    """The main job's command is one the test above parses, and it runs what the README says:
    its budget ('learning FetchReach in 30,000 steps'), nu ('at its off-policy end, nu = 1') and
    its first evaluation ('from the first one on (2,500 steps)')."""
    said = re.search(r"learning FetchReach in ([\d,]+) steps:\n\n```bash\n(.*?)\n```", README)
    nu = re.search(r"off-policy end, nu = ([\d.]+)", README)
    first_eval = re.search(r"from the first one on \(([\d,]+) steps\)", README)
    assert said and nu and first_eval, "the main job's paragraph no longer says what this checks"
    assert said[2] in COMMANDS
    script, *argv = shlex.split(said[2])[1:]
    args = parsed(capsys, script, argv)
    assert script == "ipg_her.py" and args.env_id == "FetchReach-v4"
    assert args.total_timesteps == int(said[1].replace(",", ""))
    assert args.nu == float(nu[1])
    assert args.eval_freq == int(first_eval[1].replace(",", ""))


def parsed(capsys, script: str, argv: list[str]):
    """``script``'s Args for ``argv``, as its ``__main__`` parses and checks them; a refusal fails
    the test with its error line."""
    from conftest import parse

    sys.path.insert(0, str(ROOT))
    module = __import__(script.removesuffix(".py"))
    try:
        return parse(module, *argv)
    except SystemExit:
        error = capsys.readouterr().err.strip()
        pytest.fail(f"python {script} {shlex.join(argv)} is refused: {error}")
