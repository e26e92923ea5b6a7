"""The README's file map and reading guide must stay true to the code they describe.

``python tests/test_readme.py`` rewrites the map's line counts from the files.
"""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

MAPPED = ("*.py", "common/*.py", "benchmarks/*.py")  # the files the map must list


def file_rows() -> list[str]:
    """The file map's rows: ``| [`path`](path) | what | lines |``, one file each."""
    lines = (ROOT / "README.md").read_text().splitlines()
    return [line for line in lines if line.startswith("| [`")]


def test_the_file_map_gives_each_file_its_line_count():
    rows = file_rows()
    assert len(rows) >= 9
    for row in rows:
        path = re.match(r"\| \[`[^`]+`\]\(([^)]+)\) \|", row)
        assert path, f"a file-map row must start with | [`file`](file) |: {row}"
        path = path[1]
        assert (ROOT / path).is_file(), f"the README's file map lists {path}, which does not exist"
        stated = int(row.rstrip(" |").rsplit("|", 1)[1])
        actual = len((ROOT / path).read_text().splitlines())
        assert stated == actual, (
            f"README says {stated} lines for {path}, it has {actual} "
            "(python tests/test_readme.py rewrites the counts)"
        )


def test_the_file_map_lists_every_script_and_module():
    listed = {re.match(r"\| \[`[^`]+`\]\(([^)]+)\)", row)[1] for row in file_rows()}
    present = {p.relative_to(ROOT).as_posix() for pattern in MAPPED for p in ROOT.glob(pattern)}
    missing = sorted(p for p in present - listed if not p.endswith("__init__.py"))
    assert not missing, f"add these to the README's file map: {missing}"


def test_the_reading_guide_names_functions_that_exist():
    """Every `name` in "How to read the code" is a function, class or module constant of the
    code."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## How to read the code", 1)[1].split("\n## ", 1)[0]
    names = {n for n in re.findall(r"`([A-Za-z_]\w*)`", section) if not n.startswith("__")}
    assert len(names) >= 15, names
    source = "\n".join(
        p.read_text() for pattern in MAPPED for p in ROOT.glob(pattern) if p.is_file()
    )
    defined = set(re.findall(r"^\s*(?:def|class)\s+(\w+)", source, flags=re.MULTILINE))
    defined |= set(re.findall(r"^([A-Z_]+) = ", source, flags=re.MULTILINE))  # module constants
    missing = sorted(names - defined)
    assert not missing, f"the README's reading guide names what the code does not define: {missing}"


if __name__ == "__main__":  # rewrite the file map's counts
    readme = ROOT / "README.md"
    lines = readme.read_text().splitlines(keepends=True)
    for i, line in enumerate(lines):
        row = re.match(r"(\| \[`[^`]+`\]\(([^)]+)\) \|.*\| )\d+( \|\s*)$", line)
        if row and (ROOT / row[2]).is_file():
            count = len((ROOT / row[2]).read_text().splitlines())
            lines[i] = f"{row[1]}{count}{row[3]}"
    readme.write_text("".join(lines))
