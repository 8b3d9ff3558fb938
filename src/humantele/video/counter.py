"""A frame counter drawn into a frame at capture and read back from the decoded frame.

For glass-to-glass latency: the sender draws the frame's number into its top-left corner, the
receiver reads it from the decoded picture and matches it to the capture time. The code is a
block code that survives lossy video coding (VP8, H.264 at a few hundred kbit/s): 32 cells of
``cell`` x ``cell`` px (default 8, aligned with the codecs' 8x8 blocks), 8 per row, 4 rows, a
64 x 32 px patch. Cells are black (0) or white (255), read from the mean grey of each cell's
middle half: a cell darker than 88 is 0, brighter than 168 is 1, anything between makes the
whole read fail (a frame without a counter, or one the codec smeared).

Layout, row-major from the top-left cell: cells 0-23 the counter's 24 bits, most significant
first (``seq mod 2**24``: 7.7 days at 25 fps); cells 24-31 an 8-bit check, the low byte of
``zlib.crc32`` of the counter's 3 bytes. A corrupted frame passes the check with probability
1/256 at most; a frame whose check fails reads as None.
"""

from __future__ import annotations

import zlib

import cv2
import numpy as np
from numpy.typing import NDArray

BITS = 24
CHECK_BITS = 8
COLS, ROWS = 8, 4
CELL = 8
MODULUS = 1 << BITS
LOW, HIGH = 88.0, 168.0  # grey levels: below is a 0 cell, above a 1 cell


def _check(value: int) -> int:
    return zlib.crc32(value.to_bytes(3, "big")) & ((1 << CHECK_BITS) - 1)


def _cells(value: int) -> list[int]:
    v = value % MODULUS
    bits = [(v >> (BITS - 1 - i)) & 1 for i in range(BITS)]
    c = _check(v)
    check = [(c >> (CHECK_BITS - 1 - i)) & 1 for i in range(CHECK_BITS)]
    return [*bits, *check]


def patch_size(cell: int = CELL) -> tuple[int, int]:
    """(width, height) in px of the counter patch."""
    return (COLS * cell, ROWS * cell)


def draw_counter(image: NDArray[np.uint8], value: int, cell: int = CELL) -> None:
    """Draw ``value mod 2**24`` into the top-left corner of a (H, W, 3) or (H, W) uint8 image,
    in place. The image must be at least 64 x 32 px (for ``cell`` 8)."""
    w, h = patch_size(cell)
    if image.shape[0] < h or image.shape[1] < w:
        raise ValueError(f"image {image.shape[1]}x{image.shape[0]} is smaller than the counter")
    cells = np.array(_cells(value), dtype=np.uint8).reshape(ROWS, COLS) * 255
    patch = np.repeat(np.repeat(cells, cell, axis=0), cell, axis=1)
    if image.ndim == 3:
        image[:h, :w] = patch[..., None]
    else:
        image[:h, :w] = patch


def read_counter(image: NDArray[np.uint8], cell: float = CELL) -> int | None:
    """The counter in a decoded frame's top-left corner, or None when it does not read (no
    counter, a cell neither black nor white, a failed check). ``cell``: the cell size in
    this image's pixels (``CELL * decoded width / source width`` if the frame was scaled)."""
    w, h = int(round(COLS * cell)), int(round(ROWS * cell))
    if image.ndim != 2 and image.ndim != 3 or image.shape[0] < h or image.shape[1] < w:
        return None
    patch = image[:h, :w]
    if patch.ndim == 3:
        patch = cv2.cvtColor(np.ascontiguousarray(patch), cv2.COLOR_BGR2GRAY)
    means = np.empty(ROWS * COLS)
    q = cell / 4.0
    for i in range(ROWS * COLS):
        r, c = divmod(i, COLS)
        y0, x0 = int(round(r * cell + q)), int(round(c * cell + q))
        y1, x1 = (
            max(int(round((r + 1) * cell - q)), y0 + 1),
            max(int(round((c + 1) * cell - q)), x0 + 1),
        )
        means[i] = patch[y0:y1, x0:x1].mean()
    if np.any((means > LOW) & (means < HIGH)):
        return None
    bits = (means > HIGH).astype(int)
    value = 0
    for b in bits[:BITS]:
        value = (value << 1) | int(b)
    check = 0
    for b in bits[BITS:]:
        check = (check << 1) | int(b)
    return value if check == _check(value) else None


def unwrap(value: int, reference: int) -> int:
    """The full frame number nearest ``reference`` whose low 24 bits are ``value``."""
    base = reference - (reference % MODULUS) + value
    candidates = (base - MODULUS, base, base + MODULUS)
    return min(candidates, key=lambda c: abs(c - reference))
