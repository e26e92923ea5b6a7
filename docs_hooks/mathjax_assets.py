"""MkDocs hook (mkdocs.yml ``hooks:``): ship MathJax inside the built site, so the equations
render with no network, from ``file://`` too.

MathJax 3.2.2 comes from the PyPI package ``django-static-mathjax`` (pinned in
requirements-docs.txt; Apache-2.0, its LICENSE is shipped too). It installs MathJax's release
files as ``mathjax/static/mathjax/`` and needs no Django to be read. Every build adds the files
the docs load to the site under ``assets/mathjax/``: the ``tex-mml-chtml.js`` bundle that
mkdocs.yml's ``extra_javascript`` names, and the folders it loads on demand (fonts, TeX
extensions, the menu, accessibility). Nothing is vendored in git.
"""

import importlib.resources
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

SITE_DIR = "assets/mathjax"  # where the site gets them; mkdocs.yml's extra_javascript points here
BUNDLE = "tex-mml-chtml.js"  # the combined component the pages load
ON_DEMAND = ("input", "output", "ui", "a11y", "sre")  # what that bundle may load later


def mathjax_root() -> Path:
    """MathJax's release folder in the installed package (``es5/`` holds the components)."""
    try:
        root = Path(str(importlib.resources.files("mathjax"))) / "static" / "mathjax"
    except ModuleNotFoundError:
        root = None
    if root is None or not (root / "es5" / BUNDLE).is_file():
        raise PluginError("MathJax not found: pip install -r requirements-docs.txt (django-static-mathjax ships it)")
    return root


def on_files(files: Files, config: MkDocsConfig) -> Files:
    root = mathjax_root()
    es5 = root / "es5"
    sources = [es5 / BUNDLE, root / "LICENSE"]
    for folder in ON_DEMAND:
        sources += sorted(p for p in (es5 / folder).rglob("*") if p.is_file())
    for src in sources:
        rel = src.relative_to(es5 if src.is_relative_to(es5) else root).as_posix()
        files.append(File.generated(config, f"{SITE_DIR}/{rel}", abs_src_path=str(src)))
    return files
