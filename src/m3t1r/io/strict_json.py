"""Strict JSON for reports: what any strict parser reads back, and a reader as strict."""

from __future__ import annotations

import json
import math
import os

import numpy as np

__all__ = ["json_text", "parse_strict_json"]


def parse_strict_json(text: str) -> object:
    """The document of JSON `text`, refusing what Python's reader lets through: a key given twice
    in an object (the last would silently win) and the non-standard NaN and Infinity. Raises
    json.JSONDecodeError (a ValueError) for bad syntax, ValueError naming the key or constant."""

    def pairs(items: list[tuple[str, object]]) -> dict:
        document: dict = {}
        for key, value in items:
            if key in document:
                raise ValueError(f"key '{key}' given twice in one object")
            document[key] = value
        return document

    def constant(name: str) -> float:
        raise ValueError(f"'{name}' is not JSON (a strict report writes null)")

    return json.loads(text, object_pairs_hook=pairs, parse_constant=constant)


def json_text(document: object) -> str:
    """Strict JSON of `document`: NaN and infinities become `null`, numpy scalars and arrays plain.

    The result always parses with a strict parser (no `NaN`, `Infinity`); keys keep their order.
    """
    return json.dumps(_strict(document), indent=2, allow_nan=False) + "\n"


def _strict(value: object) -> object:
    if isinstance(value, dict):
        return {str(key): _strict(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(item) for item in value]
    if isinstance(value, np.ndarray):
        return [_strict(item) for item in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value
