"""Renamed keywords, attributes and module names: the old name keeps working, with a
``DeprecationWarning``.

The one implementation of a rename's transition period (control, sim and study layers use it):

* :func:`renamed_keyword` wraps a function or an ``__init__`` so that ``old=value`` is passed
  on as ``new=value`` with a warning naming both; giving both is a ``TypeError``.
* :class:`DeprecatedAttribute` is a read-only class attribute ``old`` that returns ``new``
  (``self.new``) with the same warning. On a dataclass it is not a field (no annotation), so
  ``dataclasses.replace`` and ``fields`` ignore it.
* :func:`deprecated_names` is a module's ``__getattr__`` serving old names of objects the
  module exports under their current names; its warning names the release that removes them.
"""

from __future__ import annotations

import functools
import operator
import warnings
from collections.abc import Callable
from typing import Any

__all__ = ["DeprecatedAttribute", "deprecated_names", "renamed_keyword", "warn_renamed"]


def warn_renamed(where: str, old: str, new: str, note: str = "", stacklevel: int = 3) -> None:
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
    """
    extra = f" ({note})" if note else ""
    warnings.warn(
        f"{where}: {old!r} is deprecated, use {new!r}{extra}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def renamed_keyword(old: str, new: str, note: str = "") -> Callable:
    """Decorator: the keyword ``old`` of a function is a deprecated name of ``new``.

    Decorates a function, a method or a class (its ``__init__``; place it above
    ``@dataclass``).

    Parameters
    ----------
    old, new : str
        Deprecated and current keyword names.
    note : str, optional
        What ``new`` means, for the warning.

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
    (3, "f: 'size' is deprecated, use 'length'")
    """

    def decorate(fn: Callable) -> Callable:
        if isinstance(fn, type):  # a class (e.g. a dataclass): its __init__
            fn.__init__ = decorate(fn.__init__)
            return fn
        where = fn.__qualname__.removesuffix(".__init__")

        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            if old in kwargs:
                if new in kwargs:
                    raise TypeError(
                        f"{where}: give {new!r} only ({old!r} is its deprecated name), got both"
                    )
                warn_renamed(where, old, new, note)
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
    """

    def __init__(self, new: str, note: str = "") -> None:
        self.new, self.note = new, note
        self._get = operator.attrgetter(new)

    def __set_name__(self, owner: type, name: str) -> None:
        self.old, self.owner = name, owner.__name__

    def __get__(self, obj: object, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        warn_renamed(self.owner, self.old, self.new, self.note)
        return self._get(obj)


def deprecated_names(
    module: str, names: dict[str, tuple[Any, str]], removed_in: str
) -> Callable[[str], Any]:
    """A module ``__getattr__`` for deprecated module-level names (PEP 562).

    Assign the result to the module's ``__getattr__``: an old name returns its object with a
    ``DeprecationWarning`` naming the current name and the release that removes the old one;
    any other missing name raises ``AttributeError`` as usual.

    Parameters
    ----------
    module : str
        The module's ``__name__`` (for the messages).
    names : dict
        ``{old name: (object, current dotted name)}``.
    removed_in : str
        The release without the old names, e.g. ``"0.2.0"``.

    Returns
    -------
    callable
        ``__getattr__(name)``.

    Examples
    --------
    >>> getattr_ = deprecated_names("pkg", {"size": (len, "builtins.len")}, "0.2.0")
    >>> import warnings
    >>> with warnings.catch_warnings(record=True) as w:
    ...     warnings.simplefilter("always")
    ...     getattr_("size") is len, str(w[0].message)[:52]
    (True, 'pkg.size is deprecated and will be removed in 0.2.0:')
    """
    aliases = dict(names)

    def __getattr__(name: str) -> Any:
        if name not in aliases:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        obj, current = aliases[name]
        warnings.warn(
            f"{module}.{name} is deprecated and will be removed in {removed_in}: use {current} "
            "(the same object)",
            DeprecationWarning,
            stacklevel=2,
        )
        return obj

    return __getattr__
