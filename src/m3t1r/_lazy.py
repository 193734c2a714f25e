"""`lazy`: an attribute computed on first access and then kept on the instance, without the lock that
`functools.cached_property` takes on every first access before Python 3.12 (about a microsecond, a
tenth of a warm solve's Python work)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Generic, TypeVar, overload

__all__ = ["lazy"]

T = TypeVar("T")


class lazy(Generic[T]):  # noqa: N801 - used as a decorator, spelled like `property`
    """Decorator: `build(instance)` on first access, stored in the instance's `__dict__` (frozen dataclasses
    too: the store bypasses `__setattr__`), which later accesses read directly (a non-data descriptor)."""

    def __init__(self, build: Callable[[Any], T]) -> None:
        self._build, self._name = build, build.__name__
        self.__doc__ = build.__doc__

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    @overload
    def __get__(self, instance: None, owner: type | None = None) -> lazy[T]: ...

    @overload
    def __get__(self, instance: object, owner: type | None = None) -> T: ...

    def __get__(self, instance: object | None, owner: type | None = None) -> T | lazy[T]:
        if instance is None:
            return self
        value = instance.__dict__[self._name] = self._build(instance)
        return value
