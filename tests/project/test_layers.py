"""The layers of design.md, checked on the source (AST, every import at any depth), with
the layers read from the folders (``pipeline/__init__.py`` names them):

* core: the modules of the core folders (:data:`CORE_FOLDERS`) and the shared
  ``pipeline/*.py`` modules import only numpy, scipy, threadpoolctl, numba, pure
  standard-library modules and other core modules — no files, clock, network, Prefect,
  Rerun, YAML, polars or python-control;
* nothing under ``pipeline/`` imports ``flows`` (the library never depends on its
  orchestration), and the adapters (``pipeline/adapters/``) do not import the
  composition (``pipeline/jobs/``);
* no module -- library, flows or test -- imports a private (``_name``) name of another
  module, from ``pipeline`` or ``flows``, whether by ``from m import _x`` or ``m._x``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PIPELINE = ROOT / "pipeline"
ADAPTERS, COMPOSITION_FOLDER = "adapters", "jobs"
"""The folders of design.md's layers 2 and 3."""
CORE_FOLDERS = tuple(sorted(p.name for p in PIPELINE.iterdir()
                            if p.is_dir() and (p / "__init__.py").exists()
                            and p.name not in (ADAPTERS, COMPOSITION_FOLDER)))
"""Every other package of ``pipeline`` is core (estimation, identification, readouts,
models, discrepancy, simulated)."""
FOLDER_LAYER = {**{f: "core" for f in CORE_FOLDERS}, ADAPTERS: "adapters",
                COMPOSITION_FOLDER: "composition"}


def _dotted(path: Path) -> str:
    rel = path.relative_to(PIPELINE).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


CORE = sorted(_dotted(p) for p in PIPELINE.rglob("*.py")
              if _dotted(p) and (len(p.relative_to(PIPELINE).parts) == 1
                                 or p.relative_to(PIPELINE).parts[0] in CORE_FOLDERS))
"""Core modules as dotted names under ``pipeline`` (``errors``, ``estimation.estimate``,
``discrepancy.fit``, ``discrepancy`` for its ``__init__``)."""


def _path(name: str) -> Path:
    p = PIPELINE / (name.replace(".", "/") + ".py")
    return p if p.exists() else PIPELINE / name.replace(".", "/") / "__init__.py"
# numba compiles pure numeric kernels (pipeline/models/sample_program.py); its on-disk
# cache of compiled code is the interpreter-level kind, like __pycache__, not the core's I/O
THIRD_PARTY_CORE = {"numpy", "scipy", "threadpoolctl", "numba"}
PURE_STDLIB = {"__future__", "abc", "bisect", "collections", "contextlib", "copy",
               "dataclasses", "difflib", "enum", "fractions", "functools", "graphlib",
               "heapq", "importlib", "itertools", "math", "numbers", "operator", "re",
               "statistics", "types", "typing", "warnings", "threading", "concurrent"}
"""Standard-library modules without I/O, clock or global state the core may use
(``importlib``: the lazy public names of ``pipeline/__init__.py``; ``threading`` and
``concurrent``: the estimators fit outputs and windows side by side,
``pipeline._threads.thread_map``, with results that do not depend on the thread count --
tests/estimation/test_threads.py)."""
CORE_EXCEPTIONS = {"_threads": {"os"}}
"""One module may import one more: ``pipeline._threads`` reads how many cores the process
may run on (``os.sched_getaffinity``) to decide its thread count; nothing else of ``os``."""


def _imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, imported names) of every import in ``path``, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, a.name, []) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import: resolve against the package
                base = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-node.level])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            out.append((node.lineno, mod, [a.name for a in node.names]))
    return out


def _sources(*folders: str) -> list[Path]:
    return sorted(p for f in folders for p in (ROOT / f).rglob("*.py"))


@pytest.mark.parametrize("name", CORE)
def test_core_module_imports_only_numpy_scipy_and_core(name):
    bad = []
    for line, mod, names in _imports(_path(name)):
        top = mod.split(".")[0]
        if top in THIRD_PARTY_CORE or top in PURE_STDLIB or \
                top in CORE_EXCEPTIONS.get(name, ()):
            continue
        inner = mod.split(".", 1)[1] if "." in mod else ""
        if top == "pipeline" and (inner in CORE or (
                (mod == "pipeline" or inner in CORE_FOLDERS)  # `from pipeline.x import m`
                and all(n in CORE or f"{inner}.{n}" in CORE for n in names))):
            continue
        bad.append(f"{name}.py:{line}: {mod} {names or ''}")
    assert not bad, "core modules import outside the core:\n" + "\n".join(bad)


def test_the_library_never_imports_flows_and_adapters_not_composition():
    bad = []
    for path in _sources("pipeline"):
        rel = path.relative_to(ROOT)
        for line, mod, _ in _imports(path):
            if mod.split(".")[0] == "flows":
                bad.append(f"{rel}:{line}: imports {mod}")
            if rel.parts[1] == ADAPTERS and mod.startswith("pipeline.") and \
                    mod.split(".")[1] == COMPOSITION_FOLDER:
                bad.append(f"{rel}:{line}: adapter imports composition module {mod}")
    assert not bad, "\n".join(bad)


def test_no_module_imports_a_private_name_of_another():
    """Library, flows and the tests alike: a test checks a rule through its public name
    (a rule worth a test is worth a documented name)."""
    bad = []
    for path in _sources("pipeline", "flows") + sorted((ROOT / "tests").rglob("test_*.py")):
        rel = path.relative_to(ROOT)
        tree = ast.parse(path.read_text())
        aliases = {}  # local name -> project module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and \
                    node.module.split(".")[0] in ("pipeline", "flows"):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__") and \
                            a.name not in ("_threads", "_shipped"):
                        bad.append(f"{rel}:{node.lineno}: from {node.module} import {a.name}")
                    aliases[a.asname or a.name] = f"{node.module}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in ("pipeline", "flows"):
                        aliases[a.asname or a.name] = a.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and \
                    node.value.id in aliases and node.attr.startswith("_") and \
                    not node.attr.startswith("__"):
                bad.append(f"{rel}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not bad, "private names used across modules:\n" + "\n".join(bad)


def test_the_checks_see_the_project():
    """The lists above are not empty by accident (a moved folder would pass vacuously)."""
    assert {"estimation.estimate", "identification.search", "identification.checks",
            "readouts.frequency", "models.simulate", "discrepancy", "discrepancy.fit",
            "errors"} <= set(CORE)
    assert set(CORE_FOLDERS) == {"estimation", "identification", "readouts", "models",
                                 "discrepancy", "simulated"}
    assert not any(c.startswith(("jobs", "adapters")) for c in CORE)
    # every module of pipeline/ is in one layer: a shared top-level module or a folder's
    for p in PIPELINE.rglob("*.py"):
        rel = p.relative_to(PIPELINE)
        assert len(rel.parts) == 1 or rel.parts[0] in FOLDER_LAYER, rel
    assert len(_sources("pipeline")) >= 30 and len(_sources("flows")) >= 6


def test_source_sections_are_the_ingest_options_with_their_defaults():
    """``source.mcap`` / ``source.csv`` are the ingest adapter's options (one definition of
    the keys and defaults; the sections only add the YAML's types and bounds)."""
    import dataclasses

    from pipeline.adapters.config import CsvConfig, McapConfig
    from pipeline.adapters.ingest.options import CsvOptions, McapOptions

    for section, options in ((McapConfig, McapOptions), (CsvConfig, CsvOptions)):
        defaults = {f.name: f.default for f in dataclasses.fields(options)}
        for key, field in section.model_fields.items():
            assert key in defaults, (section.__name__, key)
            assert field.default == defaults[key], (section.__name__, key)
        # and a YAML section reaches the reader as those options
        assert options(**section().model_dump()) == options()


def test_no_module_over_800_lines_and_no_function_over_100():
    """The size goals of the layout (docs/development.md "Layout"): a module owns one concept, a
    function reads in one screen or two (lines counted with the docstring)."""
    long_modules, long_functions = [], []
    for folder in ("pipeline", "flows"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text()
            if text.count("\n") > 800:
                long_modules.append((path.name, text.count("\n")))
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    size = node.end_lineno - node.lineno + 1
                    if size > 100:
                        long_functions.append((f"{path.name}:{node.name}", size))
    assert not long_modules, long_modules
    assert not long_functions, long_functions
