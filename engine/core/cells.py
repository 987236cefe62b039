"""Claiming the cells of a grid: the one primitive of every voxel thinning (the first point met in
a cell keeps it). A grid's cells are numbered 0 .. n - 1 by the caller (voxel keys, a COPC node's
sampling grid, the cube of voxels around a scanner); the cells met so far are a bit each in an
array of uint64 words (:func:`cell_bits`), so a grid of n cells takes n / 8 bytes, whatever the
number of points."""

from __future__ import annotations

import numpy as np

from .jit import kernel

__all__ = ["cell_bits", "claim_cell", "first_in_cells"]


def cell_bits(n_cells: int) -> np.ndarray:
    """The zeroed bit array (uint64 words) of a grid of ``n_cells`` cells: no cell claimed."""
    return np.zeros((int(n_cells) + 63) // 64, dtype=np.uint64)


@kernel(inline="always")
def claim_cell(cell: int, bits: np.ndarray) -> bool:  # pragma: no cover - compiled
    """Whether ``cell`` was not claimed yet in ``bits`` (see :func:`cell_bits`); it is now."""
    word, bit = cell >> 6, np.uint64(1) << np.uint64(cell & 63)
    if bits[word] & bit:
        return False
    bits[word] |= bit
    return True


@kernel
def _claim_rows(cells: np.ndarray, bits: np.ndarray, first: np.ndarray) -> None:  # pragma: no cover - compiled
    for i in range(len(cells)):
        if claim_cell(cells[i], bits):
            first[i] = True


def first_in_cells(cells: np.ndarray, bits: np.ndarray) -> np.ndarray:
    """Boolean mask of the points (one cell index each, ``cells`` (N,) integers within the grid of
    ``bits``) that are the first, in input order, in a cell not claimed before; their cells are
    claimed in ``bits`` (so a later call with the same bits keeps out the cells taken now)."""
    first = np.zeros(len(cells), dtype=bool)
    if len(cells):
        _claim_rows(np.ascontiguousarray(cells), bits, first)
    return first
