"""The one reader of YAML (configs, sweep grids, CSV mappings, baselines, ``--set`` values and the config
text stored in results files): safe, strict and bounded. Every problem is one
:class:`~needlecli.errors.ConfigError` with the file and the line, never a traceback or a hang.

- the safe loader, and a key given twice in one mapping is an error (YAML keeps the last);
- a mapping key is a plain value (a name or a number), never a list or a mapping;
- numbers as YAML 1.2 writes them: ``1e9`` and ``2.0e-6`` are numbers (PyYAML's YAML 1.1 reads them as
  strings), ``.inf`` and ``.nan`` stay floats for the schema to reject;
- bounded: files of at most :data:`MAX_BYTES` (``/dev/zero`` or a stray data file is refused at once),
  nesting at most :data:`MAX_DEPTH` levels, at most :data:`MAX_NODES` values once aliases are expanded
  (no "billion laughs"), integers that fit in 64 bits (a 5,000-digit number is an error, not a hang);
- text only: a file with NUL bytes or that is not UTF-8 is "not a text file" (an HDF5 file given as a
  config, say).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from needlecli.errors import ConfigError

MAX_BYTES = 16 * 1024 * 1024
MAX_DEPTH = 64
MAX_NODES = 1_000_000
_INT64 = 2**63


class _Limit(yaml.YAMLError):
    """A file beyond what the reader accepts (depth, size, integer range), with where."""

    def __init__(self, problem: str, mark=None) -> None:
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


class _Loader(yaml.SafeLoader):
    """The safe loader with the rules of the module docstring."""

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self._depth = 0

    # ---- structure: depth while composing, expanded size once composed
    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Limit(f"nesting deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def get_single_data(self):
        node = self.get_single_node()
        if node is None:
            return None
        _expanded_size(node, {}, set(), 0)
        return self.construct_document(node)

    # ---- values
    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:  # the keys written in this mapping, before '<<' merges add theirs
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                kind = "a list" if isinstance(key_node, yaml.SequenceNode) else "a mapping"
                raise yaml.constructor.ConstructorError(
                    None, None, f"a key must be a plain name or number, not {kind}", key_node.start_mark)
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice in the same mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node):
        text = str(node.value).replace("_", "").lstrip("+-")
        digits = len(text)
        if digits > 25:
            raise _Limit(f"the integer of {digits} digits is too large: integers must fit in 64 bits "
                         "(write a large number as a float, e.g. 1.0e+25)", node.start_mark)
        value = super().construct_yaml_int(node)
        if not -_INT64 <= value < _INT64:
            raise _Limit(f"the integer {node.value} is too large: integers must fit in 64 bits "
                         "(write a large number as a float, e.g. 1.0e+25)", node.start_mark)
        return value


# resolvers are class-level tables: copy them before adding ours, so yaml.SafeLoader is left as it is
_Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)


def _expanded_size(node, memo: dict, active: set, depth: int) -> int:
    """How many values ``node`` makes once every alias is expanded (raises beyond :data:`MAX_NODES`, for
    a recursive alias, or for nesting through aliases deeper than twice :data:`MAX_DEPTH`)."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in active:
        raise _Limit("an alias refers to the value that contains it (a recursive structure)", node.start_mark)
    if depth > 2 * MAX_DEPTH:
        raise _Limit(f"nesting through aliases deeper than {2 * MAX_DEPTH} levels", node.start_mark)
    if isinstance(node, yaml.ScalarNode):
        n = 1
    else:
        active.add(key)
        children = node.value if isinstance(node, yaml.SequenceNode) else [c for kv in node.value for c in kv]
        n = 1
        for c in children:
            n += _expanded_size(c, memo, active, depth + 1)
            if n > MAX_NODES:
                raise _Limit(f"more than {MAX_NODES:,} values once aliases are expanded", node.start_mark)
        active.discard(key)
    memo[key] = n
    return n


def _load(text: str, source: str, loc: tuple = (), what: str = "YAML"):
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or (str(e).splitlines() or ["invalid"])[0]
        ctx, cmark = getattr(e, "context", None), getattr(e, "context_mark", None)
        if ctx and cmark is not None and mark is not None and cmark.line != mark.line:
            problem += f" ({ctx} that starts at line {cmark.line + 1})"
        kind = ("YAML error" if isinstance(e, (yaml.constructor.ConstructorError, _Limit))
                else "YAML syntax error")
        raise ConfigError(source, loc, f"{kind} {'in ' + what + ' ' if what != 'YAML' else ''}at {where}{problem}"
                          ) from None
    except RecursionError:  # a safety net: the depth limit above comes first
        raise ConfigError(source, loc, f"YAML error: nesting deeper than {MAX_DEPTH} levels") from None


def parse_yaml(text: str, source: str, what: str = "a config") -> dict:
    """Parse the YAML ``text`` of file ``source``, which must hold a mapping (``what`` it is, for messages)."""
    if len(text) > MAX_BYTES:
        raise ConfigError(source, (), f"{what} of {len(text):,} characters is larger than the {MAX_BYTES // 2**20} MiB "
                          "a YAML file may have")
    data = _load(text, source)
    if data is None:
        raise ConfigError(source, (), "the file is empty")
    if not isinstance(data, dict):
        raise ConfigError(source, (), f"{what} must be a mapping of keys, not {type(data).__name__}")
    return data


def parse_value(text: str, source: str, loc: tuple) -> Any:
    """One YAML value written on the command line (``--set key.path=value``), read as a config's values are."""
    if len(text) > MAX_BYTES:
        raise ConfigError(source, loc, "the value is too long")
    return _load(text, source, loc, what="the --set value")


def read_text(path: str | Path, what: str = "a config") -> str:
    """The text of a YAML (or other text) file: a regular file (never a folder, a named pipe or a device:
    :mod:`needlecli.io.inputs`), at most :data:`MAX_BYTES`, UTF-8, no NUL bytes. Raises
    :class:`ConfigError` naming the file (no such file, a folder, too large, binary, unreadable)."""
    from needlecli.io.inputs import read_text as read_input

    source = str(path)
    return read_input(path, what, limit=MAX_BYTES, error=lambda m: ConfigError(source, (), m), missing="no such file",
                      form="a YAML file")


def read_yaml(path: str | Path, what: str = "a config") -> tuple[dict, str]:
    """Read and parse a YAML file that holds a mapping: ``(data, text)``."""
    text = read_text(path, what)
    return parse_yaml(text, str(path), what), text
