"""Reading YAML text safely: the one parser of job and model files (used by
:mod:`pipeline.adapters.config`).

Bounded before anything is built (size, nesting depth, values counted with every alias
repetition); duplicate keys refused; a value its explicit tag cannot build
(``!!timestamp hello``, ``!!int abc``) named by its key path, line and column.  Every
error is a :class:`~pipeline.errors.ConfigError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import ConfigError

__all__ = ["MAX_YAML_BYTES", "MAX_YAML_DEPTH", "MAX_YAML_VALUES", "load_yaml_file",
           "parse_yaml_text"]


MAX_YAML_BYTES = 5_000_000
"""A job or model YAML larger than this is refused before parsing (they are kilobytes)."""
MAX_YAML_VALUES = 100_000
"""Values a YAML may expand to, counting every repetition an alias makes (a 400-byte file
of nested aliases expands to billions and took 4.9 GB before)."""
MAX_YAML_DEPTH = 40
"""Nesting levels a YAML may have (a job is 4 deep; 5000-deep brackets overflowed the
parser's recursion)."""


class _BadValue(Exception):
    """A scalar whose explicit tag (``!!timestamp hello``) its constructor cannot build."""

    def __init__(self, node, exc: BaseException) -> None:
        super().__init__(str(exc))
        self.node, self.exc = node, exc


_TAG_WANTS = {"timestamp": "a date or time such as 2026-03-01 or 2026-03-01T12:00:00Z",
              "int": "an integer such as 42", "float": "a number such as 0.5",
              "bool": "true or false"}


def _key_path(root, target) -> str:
    """The dotted key path (``source.timezone``, ``windows[2]``) of ``target`` in ``root``."""
    stack = [(root, "")]
    while stack:
        node, path = stack.pop()
        if node is target:
            return path or "(top level)"
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                name = k.value if isinstance(k, yaml.ScalarNode) else "?"
                stack.extend([(k, f"{path}.{name}".lstrip(".")),
                              (v, f"{path}.{name}".lstrip("."))])
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((v, f"{path}[{i}]") for i, v in enumerate(node.value))
    return "(unknown key)"


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (last-wins silently is a lost setting) and
    reports a value its explicit tag cannot build (``!!timestamp hello``) by its node."""

    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep=deep)
        except ConfigError:
            raise
        except (ValueError, TypeError, AttributeError, KeyError, OverflowError) as exc:
            raise _BadValue(node, exc) from None

    def construct_mapping(self, node, deep=False):
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue  # pydantic reports unhashable keys with their path
            if key in seen:
                first = seen[key]
                raise ConfigError(
                    f"{getattr(self, 'where', 'YAML')}: duplicate key {key!r} at line "
                    f"{key_node.start_mark.line + 1} (first at "
                    f"line {first.start_mark.line + 1}); a YAML mapping keeps only the last "
                    "one — remove or merge the duplicate")
            seen[key] = key_node
        return super().construct_mapping(node, deep=deep)


def _check_tree(root, where: str) -> None:
    """Bound the expanded size (aliases counted every time they are used) and the depth
    of a composed YAML node graph without expanding it."""
    sizes: dict[int, int] = {}
    stack = [(root, 0, False)]
    while stack:
        node, depth, done = stack.pop()
        if depth > MAX_YAML_DEPTH:
            raise ConfigError(
                f"{where}: nesting deeper than {MAX_YAML_DEPTH} levels at line "
                f"{node.start_mark.line + 1}; a job YAML needs a handful — flatten it")
        children = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for kv in node.value for n in kv]
        if done:
            total = 1 + sum(sizes[id(c)] for c in children)
            sizes[id(node)] = total
            if total > MAX_YAML_VALUES and len(sizes) >= MAX_YAML_VALUES:
                raise ConfigError(  # written out, not repeated by aliases
                    f"{where}: the YAML at line {node.start_mark.line + 1} holds more than "
                    f"{MAX_YAML_VALUES:,} values; a job or model YAML needs far fewer (a model "
                    "has at most 100 blocks) — check that this is the file you meant")
            if total > MAX_YAML_VALUES:
                raise ConfigError(
                    f"{where}: the YAML at line {node.start_mark.line + 1} expands to more "
                    f"than {MAX_YAML_VALUES:,} values (anchors and aliases repeat what they "
                    "point to); write the values out or remove the aliases")
            continue
        if id(node) in sizes:
            continue
        stack.append((node, depth, True))
        stack.extend((c, depth + 1, False) for c in children if id(c) not in sizes)


def parse_yaml_text(text: str, where: str) -> Any:
    """Parse YAML with the limits above and duplicate keys refused (the only parser).

    Parameters
    ----------
    text : str
        The YAML text.
    where : str
        Name of the text's origin (e.g. the file path), for error messages.
    """
    if len(text) > MAX_YAML_BYTES:
        raise ConfigError(f"{where}: {len(text):,} bytes is not a job or model YAML (limit "
                          f"{MAX_YAML_BYTES:,}); check the path")
    loader = root = None
    try:
        loader = _StrictLoader(text)
        loader.where = where
        root = loader.get_single_node()
        if root is None:
            return None
        _check_tree(root, where)
        return loader.construct_document(root)
    except _BadValue as bad:
        node, tag = bad.node, str(bad.node.tag).rsplit(":", 1)[-1]
        wants = _TAG_WANTS.get(tag, f"a value of YAML type !!{tag}")
        raise ConfigError(
            f"{where}: {_key_path(root, node)}: the value {str(node.value)[:60]!r} (line "
            f"{node.start_mark.line + 1}, column {node.start_mark.column + 1}) is tagged "
            f"!!{tag} but is not {wants}; remove the tag or write such a value") from None
    except RecursionError:
        raise ConfigError(f"{where}: nesting too deep to parse (more than "
                          f"{MAX_YAML_DEPTH} levels); a job YAML needs a handful") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{where}: malformed YAML{at}: {problem}; fix the syntax") from None
    finally:
        if loader is not None:
            loader.dispose()


def load_yaml_file(path: Path | str, *, what: str = "job file") -> Any:
    """Parse a YAML file with a clear error for missing files and syntax errors.

    Parameters
    ----------
    path : Path or str
        The YAML file (UTF-8, at most :data:`MAX_YAML_BYTES`).
    what : str
        What the file is (``"job file"``, ``"model file"``), for error messages.
    """
    p = Path(path)
    try:
        found = p.is_file()
        size = p.stat().st_size if found else 0
    except OSError as exc:  # a name too long for the file system, ...
        raise ConfigError(f"{what} {str(p)[:80]!r}: {exc.strerror or exc}; give the path to "
                          f"a .yaml {what}") from None
    if not found:
        raise ConfigError(f"{what} {str(p)!r} does not exist; give the path to a .yaml "
                          f"{what}")
    if size > MAX_YAML_BYTES:
        raise ConfigError(f"{p}: {size:,} bytes is not a {what} (limit {MAX_YAML_BYTES:,}); "
                          "check the path")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text (byte {exc.start}); save the {what} as "
                          "UTF-8") from None
    return parse_yaml_text(text, str(p))
