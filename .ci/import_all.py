"""Import every module of the product (the scripts, common/, benchmarks/ and its probes), as the
README's set-up leaves them: a package missing from requirements.txt fails here, by name."""

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OTHER_VENV = {"benchmarks.probes.td3_hopper"}  # runs in the anchors' venv (Stable-Baselines3)

sys.path.insert(0, str(ROOT))
modules = [p.stem for p in ROOT.glob("*.py")]
packages = ("common", "benchmarks", "benchmarks.probes")
modules += [f"{d}.{p.stem}" for d in packages for p in (ROOT / d.replace(".", "/")).glob("*.py")]
modules = [m for m in modules if not m.rpartition(".")[2].startswith("test_")]  # the probes' tests
for name in sorted(set(modules) - OTHER_VENV):
    importlib.import_module(name)
print(f"imported {len(set(modules) - OTHER_VENV)} modules")
