"""An open-addressing hash table of int64 keys for compiled (numba) kernels.

Kernels that group points by voxel or cube (:mod:`flowslam.compiled_voxels`, the network's
propagation, the movers' off-surface test) look keys up here instead of sorting every
point: a table twice the size of the keys it may hold, Fibonacci hashing, linear probing.
A slot is empty while its value is -1, so any int64 key may be stored; values must be
>= 0 (an index or a group number).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["empty_table", "find_slot", "number_keys", "grouped_positions"]

_FIBONACCI = np.uint64(0x9E3779B97F4A7C15)  # 2^64 / golden ratio, odd


@njit(cache=True, nogil=True)
def empty_table(n):
    """A table for up to ``n`` distinct keys: (slot keys, slot values (all -1: empty), shift
    of the hash). Look keys up with :func:`find_slot`."""
    bits = 4
    while (1 << bits) < 2 * n:
        bits += 1
    return np.zeros(1 << bits, np.int64), np.full(1 << bits, -1, np.int64), np.uint64(64 - bits)


@njit(cache=True, nogil=True)
def find_slot(slot_keys, slot_values, shift, key):
    """The slot holding ``key``, or the empty slot (value -1) where it goes: store it there
    with ``slot_keys[slot] = key; slot_values[slot] = value``."""
    mask = slot_keys.shape[0] - 1
    slot = np.int64((np.uint64(key) * _FIBONACCI) >> shift)
    while slot_values[slot] != -1 and slot_keys[slot] != key:
        slot = (slot + 1) & mask
    return slot


@njit(cache=True, nogil=True)
def number_keys(keys):
    """The distinct ``keys`` (int64) numbered in the order first met: (the table -- slot
    keys, slot numbers, shift, for :func:`find_slot` lookups --, each key's number, the
    distinct keys in number order)."""
    slot_keys, slot_number, shift = empty_table(keys.shape[0])
    number = np.empty(keys.shape[0], np.int64)
    distinct = np.empty(keys.shape[0], np.int64)
    count = 0
    for i in range(keys.shape[0]):
        slot = find_slot(slot_keys, slot_number, shift, keys[i])
        if slot_number[slot] == -1:
            slot_keys[slot], slot_number[slot] = keys[i], count
            distinct[count] = keys[i]
            count += 1
        number[i] = slot_number[slot]
    return slot_keys, slot_number, shift, number, distinct[:count]


@njit(cache=True, nogil=True)
def grouped_positions(labels, groups):
    """Positions 0..len(labels)-1 sorted by their label (0..groups-1), stable (a counting
    sort): (start (groups + 1,): group g holds ``order[start[g]:start[g + 1]]``, order)."""
    start = np.zeros(groups + 1, np.int64)
    for i in range(labels.shape[0]):
        start[labels[i] + 1] += 1
    for g in range(groups):
        start[g + 1] += start[g]
    fill = start[:-1].copy()
    order = np.empty(labels.shape[0], np.int64)
    for i in range(labels.shape[0]):
        order[fill[labels[i]]] = i
        fill[labels[i]] += 1
    return start, order
