"""A small NumPy rasteriser for ``render_mode="rgb_array"``: frames without a plotting library.

A :class:`Canvas` is an ``(height, width, 3)`` ``uint8`` image with a few antialiasing-free primitives
(segments, polylines, discs, rectangles) in pixel coordinates (``x`` to the right, ``y`` down). Each
primitive touches only its bounding box, so a frame costs well under a millisecond to a few
milliseconds. The tasks draw their states with it (:meth:`pimbrl.envs.Task.render`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["BLACK", "BLUE", "BROWN", "GREY", "RED", "Canvas", "field_frame"]

Color = tuple[int, int, int]

BLACK: Color = (0, 0, 0)
GREY: Color = (170, 170, 170)
BLUE: Color = (31, 119, 180)
RED: Color = (214, 39, 40)
BROWN: Color = (202, 152, 101)


class Canvas:
    """An RGB image to draw on; :attr:`image` is the frame."""

    def __init__(self, height: int, width: int, background: Color = (255, 255, 255)) -> None:
        self.image = np.empty((height, width, 3), dtype=np.uint8)
        self.image[:] = background

    @property
    def height(self) -> int:
        """Rows of the image."""
        return self.image.shape[0]

    @property
    def width(self) -> int:
        """Columns of the image."""
        return self.image.shape[1]

    def _box(self, x0: float, x1: float, y0: float, y1: float) -> tuple[np.ndarray, np.ndarray, slice, slice] | None:
        """Pixel-centre coordinates and slices of the clipped box ``[x0, x1] x [y0, y1]`` (``None`` if empty)."""
        c0, c1 = max(int(np.floor(x0)), 0), min(int(np.ceil(x1)) + 1, self.width)
        r0, r1 = max(int(np.floor(y0)), 0), min(int(np.ceil(y1)) + 1, self.height)
        if c0 >= c1 or r0 >= r1:
            return None
        xs = np.arange(c0, c1)[None, :] + 0.5
        ys = np.arange(r0, r1)[:, None] + 0.5
        return xs, ys, slice(r0, r1), slice(c0, c1)

    def segment(self, p0: Sequence[float], p1: Sequence[float], color: Color, width: float = 2.0) -> None:
        """A straight segment of ``width`` pixels from ``p0`` to ``p1`` (``(x, y)`` pixel coordinates)."""
        (x0, y0), (x1, y1) = p0, p1
        if not np.all(np.isfinite([x0, y0, x1, y1])):
            return
        h = width / 2
        box = self._box(min(x0, x1) - h, max(x0, x1) + h, min(y0, y1) - h, max(y0, y1) + h)
        if box is None:
            return
        xs, ys, rows, cols = box
        dx, dy = x1 - x0, y1 - y0
        length2 = dx * dx + dy * dy
        t = np.zeros(1) if length2 == 0 else np.clip(((xs - x0) * dx + (ys - y0) * dy) / length2, 0.0, 1.0)
        dist2 = (xs - x0 - t * dx) ** 2 + (ys - y0 - t * dy) ** 2
        self.image[rows, cols][dist2 <= h * h] = color  # basic slices: a view of the image

    def polyline(self, xs: np.ndarray, ys: np.ndarray, color: Color, width: float = 2.0) -> None:
        """Segments through the points ``(xs[i], ys[i])`` in order."""
        for i in range(len(xs) - 1):
            self.segment((xs[i], ys[i]), (xs[i + 1], ys[i + 1]), color, width)

    def disc(self, centre: Sequence[float], radius: float, color: Color) -> None:
        """A filled disc."""
        cx, cy = centre
        box = self._box(cx - radius, cx + radius, cy - radius, cy + radius)
        if box is None:
            return
        xs, ys, rows, cols = box
        self.image[rows, cols][(xs - cx) ** 2 + (ys - cy) ** 2 <= radius * radius] = color

    def rectangle(self, x0: float, y0: float, x1: float, y1: float, color: Color) -> None:
        """A filled axis-aligned rectangle with corners ``(x0, y0)`` and ``(x1, y1)``."""
        box = self._box(min(x0, x1), max(x0, x1) - 1, min(y0, y1), max(y0, y1) - 1)
        if box is not None:
            self.image[box[2], box[3]] = color


def field_frame(curves: Sequence[tuple[np.ndarray, Color]], scale: float, height: int = 300, width: int = 600) -> np.ndarray:
    """A line plot of 1-D fields on a shared grid: ``curves`` are ``(values, colour)``, drawn in order.

    The vertical axis spans ``[-scale, scale]`` (widened to the largest ``|value|`` if that is larger),
    with the zero line in grey; the horizontal axis spans the grid.
    """
    canvas = Canvas(height, width)
    margin = 10.0
    finite = [np.asarray(v, dtype=np.float64) for v, _ in curves]
    peak = max((float(np.max(np.abs(v[np.isfinite(v)]), initial=0.0)) for v in finite), default=0.0)
    top = max(scale, peak)
    mid = height / 2

    def to_y(v: np.ndarray) -> np.ndarray:
        return mid - v / top * (mid - margin)

    canvas.segment((margin, mid), (width - margin, mid), GREY, 1.0)
    for values, (_, color) in zip(finite, curves):
        xs = np.linspace(margin, width - margin, len(values))
        canvas.polyline(xs, to_y(values), color, 2.0)
    return canvas.image
