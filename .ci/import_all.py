"""Import every module of the product (the scripts, common/, benchmarks/), as the README's
set-up leaves them: a package missing from requirements.txt fails here, by name."""

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OTHER_VENV = {"benchmarks.td3_hopper"}  # runs in the anchors' venv (Stable-Baselines3)

sys.path.insert(0, str(ROOT))
modules = [p.stem for p in ROOT.glob("*.py")]
modules += [f"{d}.{p.stem}" for d in ("common", "benchmarks") for p in (ROOT / d).glob("*.py")]
for name in sorted(set(modules) - OTHER_VENV):
    importlib.import_module(name)
print(f"imported {len(set(modules) - OTHER_VENV)} modules")
