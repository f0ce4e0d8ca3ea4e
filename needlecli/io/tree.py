"""An HDF5 file's content in memory: :class:`Group` (arrays, attributes and nested groups), what results,
log and fit files are written from and read into. Light: no HDF5 library is imported here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class Group:
    """Arrays and attributes of one HDF5 group (nested groups as values that are ``Group``)."""

    data: dict[str, Any] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)
    dataset_attrs: dict[str, dict[str, Any]] = field(default_factory=dict)  # attributes of one dataset
