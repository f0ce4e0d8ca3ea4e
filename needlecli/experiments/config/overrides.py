"""``--set key.path=value`` overrides of a config's keys (list entries by index), applied to the parsed
YAML before the schema validates it."""

from __future__ import annotations

from typing import Any

from needlecli.errors import ConfigError
from needlecli.io.yamlfile import parse_value


def set_dotted(data: dict, dotted: str, value: Any, source: str) -> None:
    """Apply one ``--set key.path=value`` override (list indices as numbers)."""
    parts = dotted.split(".")
    cur: Any = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        key: Any = int(part) if part.isdigit() and isinstance(cur, list) else part
        if isinstance(cur, list):
            if not isinstance(key, int) or key >= len(cur):
                raise ConfigError(source, tuple(parts[: i + 1]), "no such list entry to override")
        elif not isinstance(cur, dict):
            raise ConfigError(source, tuple(parts[:i]), "is not a mapping; cannot override below it")
        if last:
            cur[key] = value
        else:
            if isinstance(cur, dict) and key not in cur:
                cur[key] = {}
            cur = cur[key]


def parse_override(ov: str, source: str) -> tuple[str, Any]:
    """``key.path=value`` as (key, value): the key a dotted path of names and list indices, the value read
    as YAML by the reader of config files (``runs.count=[1`` is a syntax error naming the key)."""
    if "=" not in ov:
        raise ConfigError(source, (), f"override {ov!r} is not of the form key.path=value")
    k, v = ov.split("=", 1)
    k = k.strip()
    parts = k.split(".")
    if not k or any(not p.strip() for p in parts):
        raise ConfigError(source, (), f"override {ov!r}: {k!r} is not a dotted key path like sensors.0.rate")
    return k, parse_value(v, source, tuple(parts))


def apply_overrides(data: dict, overrides: list[str] | None, source: str, *,
                    runs: int | None = None, seed: int | None = None) -> bool:
    """Apply ``key.path=value`` overrides (values read as YAML) and the ``--runs``/``--seed`` options to
    ``data`` in place; returns whether anything was overridden."""
    for ov in overrides or []:
        k, v = parse_override(ov, source)
        set_dotted(data, k, v, source)
    for key, value in (("count", runs), ("seed", seed)):
        if value is not None:
            data.setdefault("runs", {})
            if isinstance(data["runs"], dict):
                data["runs"][key] = value
    return bool(overrides) or runs is not None or seed is not None
