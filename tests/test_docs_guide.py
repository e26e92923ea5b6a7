"""The docs' reading guide (docs/index.md) must stay true to the code it describes: its file map
lists every script and module, and only files that exist; every name it gives is defined."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
INDEX = (ROOT / "docs" / "index.md").read_text()
MAPPED = ("*.py", "common/*.py", "benchmarks/*.py")  # the files the map must list


def section(title: str) -> str:
    return INDEX.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_file_map_lists_every_script_and_module_and_only_those_that_exist():
    listed = set(re.findall(r"^\| `([^`]+\.py)` \|", section("Files"), flags=re.MULTILINE))
    present = {p.relative_to(ROOT).as_posix() for pattern in MAPPED for p in ROOT.glob(pattern)}
    present = {p for p in present if not p.endswith("__init__.py")}
    assert not present - listed, f"add these to docs/index.md's Files: {sorted(present - listed)}"
    assert not listed - present, f"docs/index.md lists files that are gone: {listed - present}"


def test_the_reading_guide_names_functions_that_exist():
    """Every `name` in "How to read the code" is a function, class or module constant."""
    names = {n for n in re.findall(r"`([A-Za-z_]\w*)`", section("How to read the code"))}
    names -= {"diff", "if"}
    assert len(names) >= 15, names
    source = "\n".join(p.read_text() for pattern in MAPPED for p in ROOT.glob(pattern))
    defined = set(re.findall(r"^\s*(?:def|class)\s+(\w+)", source, flags=re.MULTILINE))
    defined |= set(re.findall(r"^([A-Z_]+) = ", source, flags=re.MULTILINE))  # module constants
    missing = sorted(names - defined)
    assert not missing, f"docs/index.md's reading guide names what the code does not define: {missing}"


def test_the_recipes_page_gives_the_defaults_each_task_runs_with():
    """docs/ipg_her_recipe.md's table of defaults per task is what ipg_her_recipe.py runs: parsed with no flag and
    filled in as its main does, each row's sigma target at the start, its target from the end of the decay on, its
    discount and its grasped starts."""
    import numpy as np

    import ipg_her_recipe as recipe
    from common import cli

    page = (ROOT / "docs" / "ipg_her_recipe.md").read_text()
    rows = [line for line in page.split("| task | $d$, $H$ |", 1)[1].split("\n\n", 1)[0].splitlines()[2:]]
    envs = {
        "FetchReach, FetchPush, FetchSlide": ("FetchReach-v4", "FetchPush-v4", "FetchSlide-v4"),
        "FetchPickAndPlace": ("FetchPickAndPlace-v4",),
        "HandReach": ("HandReach-v3",),
        "HandManipulateBlockRotateZ": ("HandManipulateBlockRotateZ-v1",),
        "PointMaze_Medium": ("PointMaze_Medium-v3",),
        "a task without goals (Hopper-v5)": ("Hopper-v5",),
    }
    assert [row.split(" | ")[0].strip("| ") for row in rows] == list(envs)
    for row in rows:
        task, _, start, later, gamma, grasped = (cell.strip() for cell in row.strip("|").split(" | "))
        for env_id in envs[task]:
            args = cli.parse_args(recipe.Args, ["--env-id", env_id])
            recipe.fill_in(args)
            assert {args.target_std} == {(float(start),) * len(args.target_std)}, env_id
            end = recipe.annealed(args.target_std, args.target_std_decay, 1.0, args.target_std_floor)
            assert np.allclose(end, float(later)), env_id
            assert (args.gamma, args.grasped_start) == (pytest.approx(float(gamma), abs=5e-6), float(grasped)), env_id
