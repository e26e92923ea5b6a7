"""requirements.txt carries every package the product imports (the README's set-up installs it
alone): each module-level import of a third-party module in the scripts, ``common/``,
``benchmarks/`` and its probes must come from a distribution that requirements.txt names. CI
proves the same in a bare venv (``.ci/run``); this test says which import lacks its line."""

import ast
import importlib.metadata
import re
import sys

from conftest import ROOT

# run in another environment, named in their docstrings: the anchors' venv with Stable-Baselines3
OTHER_VENV = {"benchmarks/probes/td3_hopper.py"}


def product_files() -> list:
    folders = ("*.py", "common/*.py", "benchmarks/*.py", "benchmarks/probes/*.py")
    files = [f for pattern in folders for f in ROOT.glob(pattern) if not f.stem.startswith("test_")]
    return [f for f in files if f.relative_to(ROOT).as_posix() not in OTHER_VENV]


def module_level_imports(path) -> set[str]:
    """Top-level names imported by the statements at a module's top level (not in functions:
    those are the optional ones, each refused with an install hint where it is used)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


def required_distributions() -> set[str]:
    lines = (ROOT / "requirements.txt").read_text().splitlines()
    names = [re.split(r"[=<>~! ;\[]", line.strip())[0] for line in lines]
    return {normalise(n) for n in names if n and not n.startswith(("#", "-"))}


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_imported_package_is_in_requirements_txt():
    local = {p.stem for p in ROOT.glob("*.py")} | {"common", "benchmarks", "conftest"}
    providers = importlib.metadata.packages_distributions()
    required, missing = required_distributions(), []
    for path in product_files():
        for name in module_level_imports(path) - set(sys.stdlib_module_names) - local:
            distributions = {normalise(d) for d in providers.get(name, [name])}
            if not distributions & required:
                missing.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not missing, "not in requirements.txt: " + "; ".join(sorted(missing))
