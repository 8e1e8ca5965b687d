"""The documentation site (issue 35, build 6): ``mkdocs build --strict`` is green, the
README stays a short entry point, every page is in the navigation, and every public
parameter of ``pipeline/`` and ``flows/`` appears in the generated API reference.

The site is built once for the module (about 12-20 s on two shared cores) into a temporary
folder; nothing is written into the checkout.
"""

from __future__ import annotations

import ast
import html
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.project.test_docstrings import _public_callables, documented_parameters

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
REFERENCE = DOCS / "reference"
README_MAX_LINES = 300

_DIRECTIVE = re.compile(r"^:::\s+(?P<module>[\w.]+)\s*$", re.M)
_HEADING_ID = re.compile(r'id="(?P<id>[^"]+)" class="doc doc-heading"')
_PARAMETERS_TABLE = re.compile(
    r'doc-section-title">Parameters:</span>.*?<tbody>(?P<body>.*?)</tbody>', re.S)
_FIRST_CELL = re.compile(r'<tr class="doc-section-item">\s*<td>\s*<code>(?P<name>[^<]+)</code>')


def _nav_pages(nav) -> list[str]:
    """Every page path in the ``nav`` of mkdocs.yml (nested sections flattened)."""
    out = []
    for item in nav:
        if isinstance(item, str):
            out.append(item)
        elif isinstance(item, dict):
            for value in item.values():
                out.extend(_nav_pages(value) if isinstance(value, list) else [value])
    return out


def _config() -> dict:
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text())


def _public_modules() -> list[str]:
    """Dotted names of every module of pipeline/ and flows/ without a private part."""
    mods = []
    for top in ("pipeline", "flows"):
        for p in sorted((ROOT / top).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if not any(x.startswith("_") and x != "__main__" for x in parts):
                mods.append(".".join(parts))
    return mods


def _module_path(module: str) -> Path:
    base = ROOT.joinpath(*module.split("."))
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def _referenced_modules() -> dict[str, str]:
    """``module -> reference page stem`` for every ``::: module`` directive."""
    out = {}
    for page in sorted(REFERENCE.glob("*.md")):
        for m in _DIRECTIVE.finditer(page.read_text()):
            out[m.group("module")] = page.stem
    return out


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built by ``mkdocs build --strict`` (a warning fails it)."""
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                        str(out)], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, f"mkdocs build --strict failed:\n{r.stdout}\n{r.stderr}"
    return out


def test_mkdocs_build_strict_is_green(site):
    assert (site / "index.html").is_file()
    assert (site / "reference" / "estimation" / "index.html").is_file()


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines (at most {README_MAX_LINES})"


def test_every_page_is_in_the_nav_and_every_nav_page_exists():
    nav = _nav_pages(_config()["nav"])
    assert len(nav) == len(set(nav)), "a page is listed twice in the nav"
    missing = [p for p in nav if not (DOCS / p).is_file()]
    assert not missing, f"nav pages that do not exist: {missing}"
    pages = sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
    omitted = sorted(set(pages) - set(nav))
    assert not omitted, f"docs pages not in the nav of mkdocs.yml: {omitted}"


def test_the_readme_links_and_images_exist():
    text = (ROOT / "README.md").read_text()
    targets = [t.split("#")[0] for t in re.findall(r"\]\(([^)\s]+)\)", text)
               if not t.startswith(("http://", "https://", "#"))]
    assert targets
    missing = [t for t in targets if not (ROOT / t).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"


def test_every_public_module_has_a_reference_entry():
    referenced = _referenced_modules()
    missing = sorted(set(_public_modules()) - set(referenced))
    assert not missing, f"modules without a ::: entry in docs/reference/: {missing}"
    unknown = sorted(m for m in referenced if not _module_path(m).is_file())
    assert not unknown, f"::: entries naming no module: {unknown}"


def _rendered_parameters(page_html: str) -> dict[str, set[str]]:
    """``object id -> parameter names`` of every object's Parameters table on a page."""
    heads = list(_HEADING_ID.finditer(page_html))
    out = {}
    for k, h in enumerate(heads):
        end = heads[k + 1].start() if k + 1 < len(heads) else len(page_html)
        names = set()
        for table in _PARAMETERS_TABLE.finditer(page_html, h.end(), end):
            names.update(html.unescape(n.group("name")).strip().lstrip("*")
                         for n in _FIRST_CELL.finditer(table.group("body")))
        out[h.group("id")] = names
    return out


def test_every_public_parameter_is_in_the_api_reference(site):
    """For every public function and method of every public module (the callables
    ``tests/project/test_docstrings.py`` checks), each documented parameter is a row of that
    object's Parameters table on its reference page."""
    rendered: dict[str, dict[str, set[str]]] = {}
    problems, checked = [], 0
    for module, stem in sorted(_referenced_modules().items()):
        if stem not in rendered:
            page = site / "reference" / stem / "index.html"
            rendered[stem] = _rendered_parameters(page.read_text())
        objects = rendered[stem]
        tree = ast.parse(_module_path(module).read_text())
        for name, fn in _public_callables(tree):
            a = fn.args
            params = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs
                      if x.arg not in ("self", "cls")]
            params += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
            params = [p for p in params if p in documented_parameters(ast.get_docstring(fn))]
            if not params:
                continue
            ident = f"{module}.{name}"
            if ident not in objects:
                problems.append(f"{ident}: not on reference/{stem}.md")
                continue
            checked += 1
            missing = [p for p in params if p not in objects[ident]]
            if missing:
                problems.append(f"{ident}: parameters not rendered {missing}")
    assert checked > 300, checked
    assert not problems, "API reference gaps:\n" + "\n".join(problems)


def test_the_fixed_core_api_is_documented_with_every_parameter(site):
    """The design's fixed core API, parameter by parameter (design.md "Python core API")."""
    page = (site / "reference" / "estimation" / "index.html").read_text()
    params = _rendered_parameters(page)["pipeline.estimation.estimate.estimate_step_responses"]
    assert {"x", "y", "n_p", "dt", "integrating", "noise", "n_k", "instruments"} <= params


def test_the_documentation_images_are_the_screenshot_copies():
    """The pages show the copies the report and viewer tests refresh (docs/images/)."""
    from tests.readme_images import DOCS_IMAGES

    shown = set()
    for page in DOCS.rglob("*.md"):
        for t in re.findall(r"!\[[^\]]*\]\(([^)\s]+\.png)\)", page.read_text()):
            target = (page.parent / t).resolve()
            assert target.is_file(), (page, t)
            shown.add(target)
    assert shown and all(p.parent == DOCS_IMAGES for p in shown)
    assert {p.name for p in shown} == {"report_demo.png", "report_discrepancy.png",
                                       "viewer_steps.png", "viewer_signals.png"}
