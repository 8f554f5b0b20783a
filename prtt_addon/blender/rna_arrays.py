"""Blender's per-element data as numpy arrays, sized from the data itself.

``foreach_get``/``foreach_set`` want a buffer of exactly the collection's
length times the attribute's width. Sizing it from another count (loops for a
UV layer, loop triangles for corners, an image's size for its pixels) breaks
where the two differ: a UV layer of a mesh in edit mode has no elements
(its data lives in the edit mesh), an image whose file is missing has no
pixels. Every read and write on the Blender side goes through here, so such a
case is a clear ``RnaArrayError`` naming what was read, not a ``TypeError``
from inside Blender.
"""
from __future__ import annotations

import numpy as np


class RnaArrayError(ValueError):
    """A Blender collection does not hold the elements the caller expected."""


def read(coll, attr: str, width: int = 1, dtype=np.float32, *, expect: int | None = None,
         what: str = "") -> np.ndarray:
    """``coll``'s ``attr`` as an (n, width) array (1-D when ``width`` is 1),
    n = len(coll). With ``expect``, n must equal it (RnaArrayError naming
    ``what`` otherwise)."""
    n = len(coll)
    if expect is not None and n != expect:
        raise RnaArrayError(f"{what or attr}: {n} elements where {expect} were expected")
    a = np.empty(n * width, dtype)
    if n:
        coll.foreach_get(attr, a)
    return a.reshape(n, width) if width > 1 else a


def write(coll, attr: str, values, width: int = 1, dtype=np.float32, *, what: str = "") -> None:
    """Set ``coll``'s ``attr`` from ``values`` ((n, width) or flat), which must
    hold exactly len(coll) x ``width`` numbers (RnaArrayError otherwise:
    nothing is written)."""
    flat = np.ascontiguousarray(values, dtype).ravel()
    n = len(coll)
    if flat.size != n * width:
        raise RnaArrayError(f"{what or attr}: {flat.size // max(width, 1)} values for {n} elements")
    if n:
        coll.foreach_set(attr, flat)


def read_pixels(image) -> np.ndarray:
    """An image's pixels as (H, W, C) float32, bottom row first (Blender's
    order; 0 x 0 for an image Blender could not load). RnaArrayError when
    the image holds other than its size's pixels."""
    w, h = (int(s) for s in image.size)
    c = int(image.channels)
    n = len(image.pixels)
    if n != w * h * c:
        raise RnaArrayError(f"image {image.name!r} has no pixel data of its size {w}x{h}x{c} "
                            f"(its file {image.filepath!r} missing or unreadable?)")
    px = np.empty(n, np.float32)
    image.pixels.foreach_get(px)
    return px.reshape(h, w, c)


def write_pixels(image, rgba) -> None:
    """Set an image's pixels from (H, W, C) values, bottom row first; the shape
    must be the image's (RnaArrayError otherwise: nothing is written)."""
    w, h = (int(s) for s in image.size)
    c = int(image.channels)
    flat = np.ascontiguousarray(rgba, np.float32).ravel()
    if flat.size != w * h * c or len(image.pixels) != flat.size:
        raise RnaArrayError(f"image {image.name!r}: {np.shape(rgba)} pixels for an image of "
                            f"{w}x{h}x{c}")
    image.pixels.foreach_set(flat)
