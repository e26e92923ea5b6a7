"""The README's file table states each file's length: it must be the file's."""

import re

from conftest import ROOT


def test_the_file_table_gives_each_listed_file_its_line_count():
    rows = [
        line for line in (ROOT / "README.md").read_text().splitlines() if line.startswith("| [`")
    ]
    assert len(rows) >= 9
    for row in rows:
        paths = re.findall(r"\]\(([^)]+\.py)\)", row)
        if not paths:  # the benchmarks/ row names a folder, then its scripts in `name.py` form
            paths = ["benchmarks/" + name for name in re.findall(r"`(\w+\.py)`", row)]
        counts = [int(n) for n in row.rstrip(" |").rsplit("|", 1)[1].split(",")]
        actual = [len((ROOT / p).read_text().splitlines()) for p in paths]
        assert counts == actual, f"README says {counts} lines for {paths}, they have {actual}"
