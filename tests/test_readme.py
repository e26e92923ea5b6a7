"""The README is the product's first minute: its set-up line and test command are the ones CI
runs, every file it links exists, and every script it shows a command of accepts that command's
flags."""

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


COMMANDS = [line.split("#")[0].strip() for block in bash_blocks() for line in block.splitlines()
            if line.startswith("python ") and line.split()[1].endswith(".py")]  # fmt: skip


@pytest.mark.parametrize("command", COMMANDS)
def test_every_script_command_parses(command):
    """The flags of each ``python script.py ...`` line are the script's: parsed and checked as
    its ``__main__`` does, nothing run."""
    from conftest import parse

    script, *argv = shlex.split(command)[1:]
    sys.path.insert(0, str(ROOT))
    module = __import__(script.removesuffix(".py"))
    parse(module, *argv)
