"""The docs' reading guide (docs/index.md) must stay true to the code it describes: its file map
lists every script and module, and only files that exist; every name it gives is defined."""

import re
from pathlib import Path

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
