"""The docs site renders its maths, and searches, with no network and from file://.

Builds the site (``mkdocs build --strict``, as CI does), opens pages from ``file://`` in headless
Chromium with every host name unresolvable, and reads the DOM after the scripts ran: each
equation that pymdownx.arithmatex marked must have become a MathJax ``mjx-container``, with no
TeX error and no raw ``\\(`` left. Chromium comes from Debian (``apt-get install -y chromium``);
without it this module skips, except under CI (``CI=true``), where it fails.
"""

import html
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MATHS_PAGE = "ppo_kl.html"  # docs/ppo_kl.md: inline and display equations
BROWSERS = ("chromium", "chromium-browser", "google-chrome")
INSTALL = "apt-get install -y chromium"


def need(what: str) -> None:
    """Skip for lack of ``what``, but fail under CI: there the check must really run."""
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI=true but {what}")
    pytest.skip(what)


@pytest.fixture(scope="module")
def browser() -> str:
    path = next(filter(None, map(shutil.which, BROWSERS)), None)
    if path is None:
        need(f"no headless browser to render the docs ({' / '.join(BROWSERS)}): {INSTALL}")
    return path


@pytest.fixture(scope="module")
def site(tmp_path_factory, browser) -> Path:
    """The site as CI builds it (``mkdocs build --strict``), in a fresh folder."""
    try:
        import mkdocs  # noqa: F401
    except ImportError:
        need("mkdocs is not installed: pip install -r requirements-docs.txt")
    out = tmp_path_factory.mktemp("site")
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(out)]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


def dump_dom(browser: str, page: Path, tmp_path: Path, query: str = "") -> str:
    """The page's DOM after its scripts ran, opened from file:// with no network: every host
    name fails to resolve, so anything not inside the built site cannot load."""
    cmd = [
        browser,
        "--headless",
        "--no-sandbox",  # CI runs as root
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
        "--host-resolver-rules=MAP * ~NOTFOUND",
        "--virtual-time-budget=20000",
        "--dump-dom",
        page.as_uri() + query,
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def text_of(dom: str) -> str:
    """The visible text: no <style>/<script> contents, no tags, entities decoded."""
    dom = re.sub(r"<(style|script)\b.*?</\1>", "", dom, flags=re.S | re.I)
    return html.unescape(re.sub(r"<[^>]+>", "", dom))


def maths_problems(built: str, dom: str) -> list[str]:
    """What is wrong with the maths of a page: ``built`` its HTML as built, ``dom`` as rendered.
    An empty list means every equation rendered."""
    marked = len(re.findall(r'class="arithmatex"', built))
    rendered = len(re.findall(r'class="arithmatex">\s*<mjx-container\b', dom))
    problems = []
    if marked == 0:
        problems.append("the built page has no arithmatex equations to check")
    if rendered != marked:
        problems.append(f"{rendered} of {marked} equations rendered as mjx-container")
    if "<mjx-merror" in dom:
        problems.append("MathJax reported a TeX error (mjx-merror)")
    text = text_of(dom)
    for raw in (r"\(", r"\["):
        if raw in text:
            at = text.index(raw)
            problems.append(f"raw TeX left in the text: {text[at : at + 60]!r}")
    return problems


def external_refs(built: str) -> list[str]:
    """Scripts, stylesheets and fonts a page loads from outside the site."""
    refs = re.findall(r'<(?:script|link)\b[^>]*?(?:src|href)="([^"]+)"', built)
    return [r for r in refs if re.match(r"([a-z]+:)?//", r, flags=re.I)]


def test_maths_renders_offline_from_file(site, browser, tmp_path):
    page = site / MATHS_PAGE
    built = page.read_text(encoding="utf-8")
    assert external_refs(built) == [], "the page loads files from outside the built site"
    assert "assets/mathjax/tex-mml-chtml.js" in built
    assert (site / "assets/mathjax/tex-mml-chtml.js").is_file()
    assert (site / "assets/mathjax/output/chtml/fonts/woff-v2").is_dir()  # MathJax's TeX fonts
    assert maths_problems(built, dump_dom(browser, page, tmp_path)) == []


def test_the_check_catches_maths_that_did_not_render(site, browser, tmp_path):
    """The same page with MathJax's script pointing at a missing file must fail the check."""
    built = (site / MATHS_PAGE).read_text(encoding="utf-8")
    broken = built.replace("assets/mathjax/tex-mml-chtml.js", "assets/mathjax/missing.js")
    assert broken != built
    page = site / "broken_maths.html"  # beside the real page, so every other path still works
    page.write_text(broken, encoding="utf-8")
    problems = maths_problems(broken, dump_dom(browser, page, tmp_path))
    assert any("equations rendered" in p for p in problems), problems
    assert any("raw TeX" in p for p in problems), problems


def test_search_works_offline_from_file(site, browser, tmp_path):
    """Material's offline plugin (search index inlined as a script) and the local
    iframe-worker shim: a search from file:// finds pages."""
    assert external_refs((site / "index.html").read_text(encoding="utf-8")) == []
    dom = dump_dom(browser, site / "index.html", tmp_path, query="?q=advantage")
    assert len(re.findall(r'class="md-search-result__item', dom)) > 0, "no search results"
