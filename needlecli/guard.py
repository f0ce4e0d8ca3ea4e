"""Calls into component code, guarded: the one place where a component's failure becomes a message.

Every call the experiments make into a component -- a model simulated, a sensor measuring, an observer's
``check``, ``initial_estimate`` and ``run``, a controller acting -- goes through a :class:`Component`,
built-in or a lab's plug-in alike. Whatever the call raises, ``SystemExit`` (``sys.exit``) included,
becomes one :class:`~needlecli.errors.ComponentError` naming the component, its config name and type,
and the package it comes from (:meth:`needlecli.registry.Registry.origin`)::

    observer 'my' (type bad_ukf, package needle-bad-ukf): run raised ValueError: boom

These go through untouched: ``KeyboardInterrupt`` (Ctrl-C, and the SIGINT / SIGTERM that
:mod:`needlecli.io.atomic` raises as :class:`~needlecli.errors.Interrupted`) and any exception a signal's
exception was wrapped into on its way out (its cause or context), so that a stopped run still ends as
one; ``MemoryError`` (the memory estimate's message); a :class:`~needlecli.errors.NeedleError`, already
the user's one line. What a call returns is checked against the problem by the contract of the
component's role (:mod:`needlecli.observers.contract`, :mod:`needlecli.sensors.contract`) through
:meth:`Component.returned`, and a problem found there is one line too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from needlecli.errors import ComponentError, NeedleError

if TYPE_CHECKING:
    from needlecli.registry import Registry

R = TypeVar("R")

#: what a guard lets through unchanged (see the module's docstring)
PASS_THROUGH = (NeedleError, KeyboardInterrupt, MemoryError, GeneratorExit)
MAX_TEXT = 400  # characters of a failure's own message kept in the one line


@dataclass(frozen=True)
class Component:
    """One configured component, as messages name it.

    Attributes
    ----------
    kind : str
        Its role: ``"observer"``, ``"sensor"``, ``"model"``, ``"controller"``, ...
    name : str
        Its name in the config (the type when the config gives none).
    type : str
        Its registered type.
    package : str
        The distribution it comes from: ``needlecli`` or a plug-in's package.
    """

    kind: str
    name: str
    type: str
    package: str

    @classmethod
    def of(cls, registry: Registry, type_: str, name: str | None = None) -> Component:
        """The component of ``registry`` registered as ``type_``, named ``name`` in the config."""
        return cls(registry.kind, name or type_, type_, registry.origin(type_))

    def __str__(self) -> str:
        return f"{self.kind} {self.name!r} (type {self.type}, package {self.package})"

    def call(self, what: str, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> R:
        """``fn(*args, **kwargs)``, a failure of which is a :class:`ComponentError` saying ``what`` failed
        (``"run"``, ``"measure"``, ``"check"``)."""
        try:
            return fn(*args, **kwargs)
        except PASS_THROUGH:
            raise
        except BaseException as e:  # noqa: BLE001 (SystemExit too: a component may not end the command)
            if wrapped_interrupt(e) is not None:
                raise
            raise ComponentError(str(self), f"{what} {failure(e)}") from e

    def broke(self, what: str, problem: str) -> ComponentError:
        """The error for a value that breaks the contract: ``what`` returned ``problem``."""
        return ComponentError(str(self), f"{what} returned {problem}")

    def returned(self, what: str, check: Callable[..., str | None], /, *args: Any) -> None:
        """Check what ``what`` returned: ``check(*args)`` gives the first problem in words, or None; a
        problem raises :meth:`broke`. A value so odd that the check itself fails is such a problem too."""
        try:
            problem = check(*args)
        except PASS_THROUGH:
            raise
        except Exception as e:  # noqa: BLE001 (a value the contract's own code cannot read)
            raise ComponentError(str(self), f"{what} returned a value that cannot be checked: {failure(e)}") from e
        if problem is not None:
            raise self.broke(what, problem)


def failure(e: BaseException) -> str:
    """A failure in words, one line: ``raised ValueError: boom``, ``called sys.exit(0)``."""
    if isinstance(e, SystemExit):
        return f"called sys.exit({e.code!r})" if e.code is not None else "called sys.exit()"
    text = " ".join(str(e).split())
    if len(text) > MAX_TEXT:
        text = text[: MAX_TEXT - 3] + "..."
    return f"raised {type(e).__name__}: {text}" if text else f"raised {type(e).__name__}"


def wrapped_interrupt(e: BaseException, kind: type[BaseException] = KeyboardInterrupt) -> BaseException | None:
    """The interrupt (a ``kind``: by default any KeyboardInterrupt, e.g. a signal's
    :class:`~needlecli.errors.Interrupted`) that is ``e`` or its cause or context, if any: a library turned
    it into its own exception, which the command then handles as the signal
    (:func:`needlecli.cli.common.user_errors`)."""
    seen: set[int] = set()
    x: BaseException | None = e
    while x is not None and id(x) not in seen:
        if isinstance(x, kind):
            return x
        seen.add(id(x))
        x = x.__cause__ or x.__context__
    return None


def what(v: object) -> str:
    """What a returned value is, for a message: ``None``, ``an array of shape (2, 3) (float64)``, ``a dict``."""
    if v is None:
        return "None"
    if hasattr(v, "shape") and hasattr(v, "dtype"):
        return f"an array of shape {tuple(v.shape)} ({v.dtype})"
    kind = type(v).__name__
    return f"{'an' if kind[:1].lower() in 'aeiou' else 'a'} {kind}"


def texts(v: object) -> tuple[str, ...] | None:
    """``v`` as a tuple of texts (names, units), or None when it is not a sequence of texts."""
    if isinstance(v, (str, bytes)):
        return None
    try:
        items = tuple(v)  # type: ignore[call-overload]
    except TypeError:
        return None
    return items if all(isinstance(x, str) for x in items) else None
