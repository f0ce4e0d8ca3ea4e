"""Reading YAML files (configs, sweep grids, CSV mappings, baselines) safely and strictly: the safe
loader, a key given twice is an error, and every problem is one :class:`~needlecli.errors.ConfigError`
with the file and the line."""

from __future__ import annotations

import yaml

from needlecli.errors import ConfigError


class _UniqueKeyLoader(yaml.SafeLoader):
    """The safe loader, but a key given twice in one mapping is an error (YAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:  # the keys written in this mapping, before '<<' merges add theirs
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice in the same mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, source: str, what: str = "a config") -> dict:
    """Parse the YAML ``text`` of file ``source``, which must hold a mapping (``what`` it is, for messages)."""
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        ctx, cmark = getattr(e, "context", None), getattr(e, "context_mark", None)
        if ctx and cmark is not None and mark is not None and cmark.line != mark.line:
            problem += f" ({ctx} that starts at line {cmark.line + 1})"
        what = "YAML error" if isinstance(e, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise ConfigError(source, (), f"{what} at {where}{problem}") from None
    if data is None:
        raise ConfigError(source, (), "the file is empty")
    if not isinstance(data, dict):
        raise ConfigError(source, (), f"{what} must be a mapping of keys, not {type(data).__name__}")
    return data


