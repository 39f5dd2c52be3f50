"""The type check every configuration dataclass runs on its fields: a value of the wrong kind (a string for a
number, a number for a flag) is refused naming the field, before any range check compares it."""
from __future__ import annotations

import math
import numbers
from dataclasses import fields

import numpy as np

#: an annotation's word -> (does the value fit, what it must be)
_KINDS = {
    "float": (lambda v: isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)), "a number"),
    "int": (lambda v: isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)), "a whole number"),
    "bool": (lambda v: isinstance(v, (bool, np.bool_)), "True or False"),
    "str": (lambda v: isinstance(v, str), "a string"),
    "None": (lambda v: v is None, "None"),
}


def check_field_types(obj) -> None:
    """TypeError naming the field of the dataclass ``obj`` whose value is not of its annotated kind (float, int,
    bool, str, or those or None), ValueError where a number is NaN; fields of other kinds are left to their class."""
    cls = type(obj).__name__
    for f in fields(obj):
        words = [w.strip() for w in str(f.type).split("|")]
        if not all(w in _KINDS for w in words):
            continue
        value = getattr(obj, f.name)
        if not any(_KINDS[w][0](value) for w in words):
            need = " or ".join(_KINDS[w][1] for w in words)
            raise TypeError(f"{cls}.{f.name} must be {need}, got {type(value).__name__} {value!r}"[:300])
        if isinstance(value, numbers.Real) and not isinstance(value, numbers.Integral) and math.isnan(value):
            raise ValueError(f"{cls}.{f.name} must be a number, got NaN")
