"""A closed registry of named components (models, sensors, observers, pipelines, controllers, tables, plots).

Components are added by decorating one class (or function) with ``@REGISTRY.register("name")``; configs
choose them by that short name only, never by import path.

A registry knows its names without importing the implementations: each one is created with a table
``name -> module`` of the built-in components (the module registers the name when it is imported), and
it reads the Python entry points of its group (``needlecli.observers``, ``needlecli.models``, ...) for
components that other installed packages add. An implementation is imported on first use
(:meth:`Registry.get`), so ``needle --help`` and a config that names one observer do not import all of
them. An entry point names a module (whose import registers the component) or an object in it
(``package.module:Class``), registered under the entry point's name when its module does not register it.

A registry declares what its components are (``base``: a class they subclass, named as
``"module:Class"`` and imported only when a plug-in is loaded, so that the front doors stay light; or
``callable`` for tables and plots). A plug-in that fails to import, or whose entry point gives something
else (a function where a class is needed, a number), raises :class:`PluginError` (one line naming the
entry point, its package and what it is instead) where it is used; other components and commands are
unaffected. What a component does once loaded is guarded where it is called (:mod:`needlecli.guard`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any, Generic, TypeVar

from needlecli.errors import NeedleError

T = TypeVar("T")

ENTRY_POINT_PREFIX = "needlecli."


class PluginError(NeedleError):
    """A component of an installed package (an entry point) that cannot be loaded.

    ``name`` is the component's name and ``registry`` what it is (``"observer type"``), so that a config
    check can say which key names it.
    """

    def __init__(self, message: str, *, name: str = "", registry: str = "") -> None:
        super().__init__(message)
        self.name = name
        self.registry = registry


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def _what(obj: Any) -> str:
    """What an object is, for a message: ``a function``, ``the class Foo``, ``an int (3)``, ``a module``."""
    import inspect

    if isinstance(obj, type):
        return f"the class {obj.__qualname__}"
    if isinstance(obj, type(importlib)):
        return "a module"
    if inspect.isroutine(obj):
        return "a function"
    kind = type(obj).__name__
    article = "an" if kind[:1].lower() in "aeiou" else "a"
    text = repr(obj)
    return f"{article} {kind} ({text[:40]})" if len(text) <= 40 else f"{article} {kind}"


class Registry(Generic[T]):
    """Name -> component mapping with lazy built-ins, entry points and a readable error for unknown names.

    Parameters
    ----------
    what : str
        What a component is, for messages (``"observer type"``).
    group : str, optional
        The entry-point group other packages register in (``"needlecli.observers"``).
    builtins : mapping, optional
        ``name -> module`` of the built-in components; importing the module registers the name.
    base : str or callable, optional
        What every component is: ``"module:Class"`` (each a subclass of that class; imported when a plug-in
        is loaded), or the builtin ``callable`` (each a function, or any callable object). None: anything.
    aliases : mapping, optional
        ``former name -> name`` of built-in components renamed: a former name still finds the component
        (:meth:`get`, ``in``) and :meth:`canonical` gives its name; :meth:`names` lists current names only.
    """

    def __init__(self, what: str, *, group: str | None = None, builtins: Mapping[str, str] | None = None,
                 base: str | Callable[[object], bool] | None = None, aliases: Mapping[str, str] | None = None) -> None:
        self.what = what
        self.group = group
        self.base = base
        self._builtins = dict(builtins or {})
        self.aliases = dict(aliases or {})
        if unknown := sorted(set(self.aliases.values()) - set(self._builtins)):
            raise ValueError(f"{what} aliases of no built-in: {', '.join(unknown)}")
        self._items: dict[str, T] = {}
        self._plugins: dict[str, Any] | None = None  # name -> importlib.metadata.EntryPoint, read once

    # ---------------------------------------------------------------------------------- registering
    def register(self, name: str) -> Callable[[T], T]:
        def deco(obj: T) -> T:
            if name in self._items and self._items[name] is not obj:
                raise ValueError(f"{self.what} {name!r} registered twice")
            self._items[name] = obj
            try:
                obj.registered_name = name  # type: ignore[attr-defined]
            except (AttributeError, TypeError):
                pass
            return obj

        return deco

    @property
    def kind(self) -> str:
        """What one component is called in messages about it: ``observer`` (of ``observer type``)."""
        return self.what.removesuffix(" type")

    # ---------------------------------------------------------------------------------- discovery
    def plugins(self) -> dict[str, Any]:
        """The entry points of this registry's group, by name (read once; nothing is imported)."""
        if self._plugins is None:
            self._plugins = {}
            if self.group is not None:
                from importlib.metadata import entry_points

                for ep in entry_points(group=self.group):
                    self._plugins.setdefault(ep.name, ep)
        return self._plugins

    def origin(self, name: str) -> str:
        """Where a component comes from: ``needlecli`` or the distribution that provides it."""
        if name in self._builtins or (name in self._items and name not in self.plugins()):
            return "needlecli"
        ep = self.plugins().get(name)
        dist = getattr(ep, "dist", None)
        return getattr(dist, "name", None) or (ep.value.split(":")[0].split(".")[0] if ep is not None else "?")

    def _load_plugin(self, name: str) -> None:
        ep = self.plugins()[name]
        where = f"{self.what} {name!r} of package {self.origin(name)!r} (entry point {self.group}: {ep.value})"
        if name in self._builtins or name in self.aliases:
            raise PluginError(f"{where}: the name is taken by needlecli's own {self.what}; rename the entry point",
                              name=name, registry=self.what)
        try:
            obj = ep.load()
        except Exception as e:  # noqa: BLE001 (any failure of somebody else's import is reported, not raised)
            raise PluginError(f"{where} cannot be imported: {_one_line(e)}", name=name, registry=self.what) from None
        if name not in self._items:
            if isinstance(obj, type(importlib)):  # a module that registered other names, or none
                raise PluginError(f"{where}: importing the module did not register {name!r}", name=name, registry=self.what)
            obj = self._checked(obj, where, name)
            self.register(name)(obj)
        else:  # its module registered it: the same check
            try:
                self._checked(self._items[name], where, name)
            except PluginError:
                del self._items[name]
                raise

    def _checked(self, obj: Any, where: str, name: str) -> Any:
        """``obj`` if it is what this registry's components are (:attr:`base`), else a PluginError."""
        if self.base is None:
            return obj
        if self.base is callable:
            if callable(obj):
                return obj
            raise PluginError(f"{where}: is {_what(obj)}, not a function", name=name, registry=self.what)
        module, _, attr = str(self.base).partition(":")
        cls = getattr(importlib.import_module(module), attr)
        if isinstance(obj, type) and issubclass(obj, cls):
            return obj
        raise PluginError(f"{where}: is {_what(obj)}, not a subclass of {cls.__name__}", name=name, registry=self.what)

    # ---------------------------------------------------------------------------------- lookup
    def get(self, name: str) -> T:
        """The component ``name``, importing its module on first use.

        Raises
        ------
        KeyError
            An unknown name (the message lists the known ones).
        PluginError
            A plug-in that cannot be loaded.
        """
        name = self.canonical(name)
        if name not in self._items:
            if name in self._builtins:
                importlib.import_module(self._builtins[name])
                if name not in self._items:
                    raise RuntimeError(f"module {self._builtins[name]} does not register {self.what} {name!r}")
            elif name in self.plugins():
                self._load_plugin(name)
            else:
                raise KeyError(f"unknown {self.what} {name!r}; known: {', '.join(self.names()) or 'none'}")
        return self._items[name]

    def load_all(self, plugins_only: bool = False) -> list[PluginError]:
        """Import every component (or every plug-in only); returns the plug-ins that failed (built-ins must
        not fail)."""
        failed = []
        for name in (self.plugins() if plugins_only else self.names()):
            try:
                self.get(name)
            except PluginError as e:
                failed.append(e)
        return failed

    def loaded(self) -> dict[str, T]:
        """Every component that loads (plug-ins that fail are left out: see :meth:`load_all`)."""
        self.load_all()
        return {n: self._items[n] for n in self.names() if n in self._items}

    def canonical(self, name: str) -> str:
        """The current name of a component named by a former name (:attr:`aliases`), else ``name``."""
        return self.aliases.get(name, name)

    def __contains__(self, name: object) -> bool:
        return (name in self._items or name in self._builtins or name in self.aliases
                or name in self.plugins())

    def names(self) -> list[str]:
        return sorted(set(self._items) | set(self._builtins) | set(self.plugins()))

    def builtin_names(self) -> list[str]:
        return sorted(self._builtins)

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())


def lazy_attributes(module: str, lazy: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) that imports ``name`` from ``lazy[name]`` on first use: a package
    keeps its front door light (its registry) and its contract one attribute away."""

    def __getattr__(name: str):
        if name in lazy:
            return getattr(importlib.import_module(lazy[name]), name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
