"""Every public parameter is documented (numpydoc style, checked on the source).

For each public function and public method of a public class in ``pipeline/`` and
``flows/``, every parameter (``self``/``cls`` aside; ``*args``/``**kwargs`` by name) must
appear in the docstring's ``Parameters`` section as ``name : type`` (or ``a, b : type``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted(p.relative_to(ROOT).as_posix() for f in ("pipeline", "flows")
                 for p in (ROOT / f).rglob("*.py"))
_SECTION = re.compile(
    r"^[ \t]*Parameters[ \t]*\n[ \t]*-{3,}[ \t]*\n(?P<body>.*?)"
    r"(?=^[ \t]*(?:Returns|Raises|Yields|Notes|Examples|See Also|Attributes|Warns|"
    r"References|Other Parameters)[ \t]*\n[ \t]*-{3,}|\Z)", re.S | re.M)
_ENTRY = re.compile(r"^(?P<names>\*{0,2}[A-Za-z_]\w*(?:\s*,\s*\*{0,2}[A-Za-z_]\w*)*)\s*(?::|$)")


def documented_parameters(doc: str | None) -> set[str]:
    """Names listed in the ``Parameters`` section of a numpydoc docstring."""
    m = _SECTION.search(doc or "")
    if not m:
        return set()
    body = m.group("body").splitlines()
    indent = min((len(ln) - len(ln.lstrip()) for ln in body if ln.strip()), default=0)
    names = set()
    for ln in body:
        if ln.strip() and len(ln) - len(ln.lstrip()) == indent:
            e = _ENTRY.match(ln.strip())
            if e:
                names.update(n.strip().lstrip("*") for n in e.group("names").split(","))
    return names


def _public_callables(tree: ast.Module):
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                not node.name.startswith("_"):
            yield node.name, node
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            for b in node.body:
                if isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                        not b.name.startswith("_"):
                    yield f"{node.name}.{b.name}", b


def undocumented(path: Path) -> list[str]:
    """``name: [parameters]`` for every public callable of ``path`` that misses some."""
    out = []
    for name, fn in _public_callables(ast.parse(path.read_text())):
        a = fn.args
        params = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs
                  if x.arg not in ("self", "cls")]
        params += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
        if not params:
            continue
        missing = [p for p in params if p not in documented_parameters(ast.get_docstring(fn))]
        if missing:
            out.append(f"{path.relative_to(ROOT)}:{fn.lineno} {name}: {missing}")
    return out


@pytest.mark.parametrize("module", MODULES)
def test_every_public_parameter_is_documented(module):
    missing = undocumented(ROOT / module)
    assert not missing, "undocumented parameters:\n" + "\n".join(missing)


def test_the_checker_reads_numpydoc():
    doc = """Do it.

    Parameters
    ----------
    x, y : array
        Data.
    n_p : int
        Order
        over two lines: not an entry.
    **kwargs
        Passed on.

    Returns
    -------
    z : float
    """
    assert documented_parameters(doc) == {"x", "y", "n_p", "kwargs"}
    assert documented_parameters("No sections.") == set()
