"""The teaching budgets: each script's length (``wc -l``), read in one sitting; the variant's
lines changed from its base (``diff a b | grep -c '^[<>]'``), its recipe and only that; the
README's length. The diffs between the three algorithms are whatever each one adds: reported
(``python tests/test_budgets.py``), never held to a number."""

import shutil
import subprocess

import pytest
from conftest import ROOT

LINES = {"ppo_kl.py": 380, "qprop_ppo.py": 500, "ipg_her.py": 520}  # wc -l
CHANGED = {("ipg_her.py", "ipg_her_recipe.py"): 160}  # lines starting with < or > in `diff a b`
README_LINES = 150
SCRIPTS = ["ppo_kl.py", "qprop_ppo.py", "ipg_her.py", "ipg_her_recipe.py"]


def lines(script: str) -> list[str]:
    return (ROOT / script).read_text().splitlines()


def main_block(text: list[str]) -> int:
    """The lines of the ``if __name__ == "__main__":`` block: from that line to the last
    indented (or blank) line after it."""
    start = text.index('if __name__ == "__main__":')
    end = next((i for i in range(start + 1, len(text)) if text[i][:1] not in ("", " ", "#")), len(text))
    while text[end - 1].strip() == "":
        end -= 1
    return end - start


def changed_lines(a: list[str], b: list[str]) -> int:
    """The lines a minimal diff of ``a`` to ``b`` deletes or adds: len(a) + len(b) - 2 LCS, as
    ``diff --minimal a b | grep -c '^[<>]'`` counts them (plain ``diff`` may count more: its
    heuristics trade minimality for speed)."""
    previous = [0] * (len(b) + 1)
    for line in a:
        current = [0]
        for j, other in enumerate(b):
            current.append(previous[j] + 1 if line == other else max(previous[j + 1], current[j]))
        previous = current
    return len(a) + len(b) - 2 * previous[-1]


def diff_count(a: str, b: str, *options: str) -> int:
    """``diff [options] a b | grep -c '^[<>]'``."""
    out = subprocess.run(["diff", *options, a, b], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode in (0, 1), out.stderr
    return sum(line[:1] in ("<", ">") for line in out.stdout.splitlines())


@pytest.mark.parametrize("script", LINES)
def test_each_script_stays_within_its_length(script):
    assert len(lines(script)) <= LINES[script], f"{script}: {len(lines(script))} lines"
    assert (ROOT / script).read_text().endswith("\n")  # so that wc -l counts its last line


@pytest.mark.parametrize("pair", CHANGED, ids="->".join)
def test_the_variant_changes_only_its_recipe(pair):
    """Counted in Python (no external diff needed), checked against ``diff`` where it exists:
    the count equals ``diff --minimal``'s, and the budget holds for plain ``diff``'s too."""
    a, b = pair
    counts = {"minimal": changed_lines(lines(a), lines(b))}
    if shutil.which("diff"):
        assert counts["minimal"] == diff_count(a, b, "--minimal")
        counts["diff"] = diff_count(a, b)
    assert max(counts.values()) <= CHANGED[pair], f"{a} -> {b}: {counts} changed lines"


def test_the_counts_are_diffs():
    """The helpers on small cases: a changed line is one < and one >, a moved block is counted
    as deleted and added, and the main block ends where the file's last statement does."""
    assert changed_lines(["a", "b", "c"], ["a", "x", "c"]) == 2
    assert changed_lines(["a", "b", "c"], ["a", "b", "c", "d"]) == 1
    assert changed_lines(["a", "b", "c"], ["b", "c", "a"]) == 2
    assert changed_lines([], ["a"]) == 1 and changed_lines(["a"], ["a"]) == 0
    text = ["import x", "", 'if __name__ == "__main__":', "    a = 1", "", "    b = 2", "", ""]
    assert main_block(text) == 4
    assert main_block([*text, "print(1)"]) == 4  # a later top-level line ends the block


def test_the_readme_stays_a_front_door():
    assert len((ROOT / "README.md").read_text().splitlines()) <= README_LINES


if __name__ == "__main__":  # the report: each script's length, main block and diff
    for script in SCRIPTS:
        print(f"{script}: {len(lines(script))} lines, main block {main_block(lines(script))}")
    for a, b in zip(SCRIPTS, SCRIPTS[1:], strict=False):
        print(f"diff {a} {b}: {changed_lines(lines(a), lines(b))} changed lines")
