"""Renamed dataclass fields that old user code may still pass or read.

``rename_field(cls, old, new)`` makes ``cls(old=...)`` work with a DeprecationWarning (the value goes to
``new``; giving both is a TypeError) and adds a read-only ``cls.old`` property that warns and returns
``new``.  A wrapper of the dataclass's ``__init__`` rather than an InitVar: ``dataclasses.replace`` would
pass an InitVar on, over a new value of ``new``.
"""

from __future__ import annotations

import functools
import warnings


def rename_field(cls, old: str, new: str) -> None:
    """Accept and expose the deprecated name ``old`` of the dataclass field ``new`` of ``cls``."""
    init = cls.__init__
    name = cls.__name__

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        if old in kwargs:
            value = kwargs.pop(old)
            warnings.warn(f"{name}({old}=...) is deprecated: use {new}=...", DeprecationWarning, stacklevel=2)
            if new in kwargs:
                raise TypeError(f"give {new}, not both {new} and its deprecated name {old}")
            kwargs[new] = value
        init(self, *args, **kwargs)

    def getter(self):
        warnings.warn(f"{name}.{old} is deprecated: use {new}", DeprecationWarning, stacklevel=2)
        return getattr(self, new)

    getter.__doc__ = f"Deprecated, read-only: the field is ``{new}``."
    cls.__init__ = __init__
    setattr(cls, old, property(getter))
