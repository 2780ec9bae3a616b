"""Building many instances of a frozen dataclass on a hot path.

A frozen dataclass's generated ``__init__`` sets every field through ``object.__setattr__`` (its
guard against assignment): ~1-1.7 us for the 7 fields of an :class:`~hil.vision.ellipse.Ellipse`.
A tracked stereo pair of 8 markers builds 32 ellipses and 16 ring detections, ~60 us of its
~800 us. :func:`frozen_instance` builds the same object by filling its instance dictionary: the
fields, type, equality and immutability afterwards are those of the normal constructor (asserted
for every class built this way in tests/vision/test_frozen.py). For batch builders of classes with
neither defaults nor ``__post_init__``; everything else uses the constructor.
"""

from __future__ import annotations

from typing import TypeVar

T = TypeVar("T")

_new = object.__new__


def frozen_instance(cls: type[T], fields: dict[str, object]) -> T:
    """An instance of the frozen dataclass ``cls`` whose fields are ``fields`` (every field, by
    name; copied into the instance's dict). No check: the caller passes exactly the class's
    fields (the tests compare with the constructor)."""
    obj = _new(cls)
    obj.__dict__.update(fields)
    return obj
