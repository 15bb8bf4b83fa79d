"""Deprecated names: the old one keeps working, with a ``DeprecationWarning`` naming the
release that removes it.

The one implementation of a deprecation's transition period (control, sim and study layers
use it); every deprecation declared through it is recorded in :data:`DEPRECATIONS`, which the
documentation lists (``docs/deprecations.md``, checked against this registry by a test):

* :func:`renamed_keyword` wraps a function or an ``__init__`` so that ``old=value`` is passed
  on as ``new=value`` with a warning naming both; giving both is a ``TypeError``.
* :class:`DeprecatedAttribute` is a read-only class attribute ``old`` that returns ``new``
  (``self.new``) with the same warning. On a dataclass it is not a field (no annotation), so
  ``dataclasses.replace`` and ``fields`` ignore it.
* :func:`deprecated_function` wraps a function kept for old callers.
* :func:`module_aliases` gives a module the ``__getattr__`` of its deprecated names.
* :func:`deprecated_call` warns from inside a deprecated code path (a file format).

Policy: a name deprecated in release 0.1 is removed in :data:`REMOVAL_RELEASE`.
"""

from __future__ import annotations

import functools
import importlib
import operator
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = [
    "DEPRECATIONS",
    "REMOVAL_RELEASE",
    "Deprecation",
    "DeprecatedAttribute",
    "declare",
    "deprecated_call",
    "deprecated_function",
    "module_aliases",
    "renamed_keyword",
    "warn_renamed",
]

#: The release that removes every name deprecated in 0.1.
REMOVAL_RELEASE = "0.2.0"


@dataclass(frozen=True)
class Deprecation:
    """One deprecated name.

    Attributes
    ----------
    where : str
        The function, class or module that holds it.
    old : str
        The deprecated name (a keyword, attribute, function or format).
    new : str
        What to use instead.
    kind : str
        ``"keyword"``, ``"attribute"``, ``"function"``, ``"alias"`` or ``"format"``.
    removed_in : str
        The release that removes it.
    """

    where: str
    old: str
    new: str
    kind: str
    removed_in: str = REMOVAL_RELEASE


#: Every deprecation declared (filled as the modules that declare them are imported), by
#: its public path.
DEPRECATIONS: list[Deprecation] = []


def _record(where: str, old: str, new: str, kind: str, removed_in: str) -> None:
    # The public path: private modules (``_base``) are not where a user finds the name.
    public = ".".join(p for p in where.split(".") if not p.startswith("_"))
    item = Deprecation(public, old, new, kind, removed_in)
    if item not in DEPRECATIONS:
        DEPRECATIONS.append(item)


def warn_renamed(
    where: str,
    old: str,
    new: str,
    note: str = "",
    stacklevel: int = 3,
    removed_in: str = REMOVAL_RELEASE,
) -> None:
    """Warn (``DeprecationWarning``) that ``where``'s ``old`` is now ``new``.

    Parameters
    ----------
    where : str
        The function or class, e.g. ``"IIRBank"``.
    old, new : str
        The deprecated and the current name.
    note : str, optional
        What the new name means (appended to the message).
    stacklevel : int, default 3
        Passed to :func:`warnings.warn` (3: the caller of the function that warns).
    removed_in : str
        The release that removes ``old``.
    """
    extra = f" ({note})" if note else ""
    warnings.warn(
        f"{where}: {old!r} is deprecated, use {new!r}{extra}; removed in {removed_in}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def renamed_keyword(
    old: str, new: str, note: str = "", removed_in: str = REMOVAL_RELEASE
) -> Callable:
    """Decorator: the keyword ``old`` of a function is a deprecated name of ``new``.

    Decorates a function, a method or a class (its ``__init__``; place it above
    ``@dataclass``).

    Parameters
    ----------
    old, new : str
        Deprecated and current keyword names.
    note : str, optional
        What ``new`` means, for the warning.
    removed_in : str
        The release that removes ``old``.

    Raises
    ------
    TypeError
        (from the wrapped call) When both ``old`` and ``new`` are given.

    Examples
    --------
    >>> @renamed_keyword("size", "length")
    ... def f(*, length=1):
    ...     return length
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as w:
    ...     warnings.simplefilter("always")
    ...     f(size=3), str(w[0].message)
    (3, "f: 'size' is deprecated, use 'length'; removed in 0.2.0")
    """

    def decorate(fn: Callable) -> Callable:
        if isinstance(fn, type):  # a class (e.g. a dataclass): its __init__
            fn.__init__ = decorate(fn.__init__)
            return fn
        where = fn.__qualname__.removesuffix(".__init__")
        if fn.__module__.startswith("aocontrol"):
            _record(f"{fn.__module__}.{where}", old, new, "keyword", removed_in)

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if old in kwargs:
                if new in kwargs:
                    raise TypeError(
                        f"{where}: give {new!r} only ({old!r} is its deprecated name), got both"
                    )
                warn_renamed(where, old, new, note, removed_in=removed_in)
                kwargs[new] = kwargs.pop(old)
            return fn(*args, **kwargs)

        return wrapper

    return decorate


class DeprecatedAttribute:
    """Read-only attribute ``old`` returning ``self.<new>``, with a ``DeprecationWarning``.

    Parameters
    ----------
    new : str
        The current attribute's name, or a dotted path (``"dm.modal_stroke"``).
    note : str, optional
        What it means, for the warning.
    removed_in : str
        The release that removes it.
    """

    def __init__(self, new: str, note: str = "", removed_in: str = REMOVAL_RELEASE) -> None:
        self.new, self.note, self.removed_in = new, note, removed_in
        self._get = operator.attrgetter(new)

    def __set_name__(self, owner: type, name: str) -> None:
        self.old, self.owner = name, owner.__name__
        _record(f"{owner.__module__}.{owner.__qualname__}", name, self.new, "attribute",
                self.removed_in)  # fmt: skip

    def __get__(self, obj: object, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        warn_renamed(self.owner, self.old, self.new, self.note, removed_in=self.removed_in)
        return self._get(obj)


def deprecated_function(name: str, replacement: str, removed_in: str = REMOVAL_RELEASE) -> Callable:
    """Decorator: a function kept for old callers warns that ``replacement`` replaces it.

    Parameters
    ----------
    name : str
        Its public name (``"aocontrol.study.sweep.summary_table"``).
    replacement : str
        What to call instead.
    removed_in : str
        The release that removes it.
    """

    def decorate(fn: Callable) -> Callable:
        where, _, old = name.rpartition(".")
        _record(where, old, replacement, "function", removed_in)

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            warnings.warn(
                f"{name} is deprecated: use {replacement}; removed in {removed_in}",
                DeprecationWarning,
                stacklevel=2,
            )
            return fn(*args, **kwargs)

        return wrapper

    return decorate


def module_aliases(
    module: str, aliases: dict[str, str], removed_in: str = REMOVAL_RELEASE
) -> Callable[[str], Any]:
    """The ``__getattr__`` of a module whose deprecated names alias objects elsewhere.

    Parameters
    ----------
    module : str
        The module's ``__name__``.
    aliases : dict
        Deprecated name -> ``"package.module:name"`` of the object it stands for (imported
        on first use, so an alias creates no import at load time).
    removed_in : str
        The release that removes the aliases.

    Returns
    -------
    callable
        Assign it to the module's ``__getattr__``.
    """
    for old, target in aliases.items():
        _record(module, old, target.replace(":", "."), "alias", removed_in)

    def __getattr__(name: str) -> Any:
        if name in aliases:
            mod, _, attr = aliases[name].partition(":")
            warnings.warn(
                f"{module}.{name} is deprecated: use {mod}.{attr} (the same object); "
                f"removed in {removed_in}",
                DeprecationWarning,
                stacklevel=2,
            )
            return getattr(importlib.import_module(mod), attr)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__


def deprecated_call(
    where: str, old: str, new: str, *, stacklevel: int = 3, removed_in: str = REMOVAL_RELEASE
) -> None:
    """Warn from inside a deprecated path (a call or format with no name of its own).

    Declare it at import time with :func:`declare` so that :data:`DEPRECATIONS` lists it.
    """
    _record(where, old, new, "format", removed_in)
    warnings.warn(
        f"{where}: {old} is deprecated: {new}; removed in {removed_in}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def declare(
    where: str, old: str, new: str, kind: str = "format", removed_in: str = REMOVAL_RELEASE
) -> None:
    """Record at import time a deprecation warned by hand (:func:`deprecated_call`, or
    :func:`warn_renamed` for keywords a decorator cannot express)."""
    _record(where, old, new, kind, removed_in)
