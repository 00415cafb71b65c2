"""Fuzz the readers (KITTI .bin, PCD, PLY, NPY, PointCloud2, TUM/KITTI trajectories) with
generated valid and broken inputs (``fuzz_inputs``): every input gives a valid result whose
size agrees with the header and the data, or an ``InputError`` of one line; never another
exception, never a silent truncation.

Bounded for CI (deterministic: ``derandomize=True``; about 20 s for the file on a 2-core
machine); ``tools/fuzz_readers.py`` runs the same generators for longer. The numbers of
inputs tried are printed at the end (``-s``) and checked to be what was asked.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
import fuzz_inputs
from fuzz_inputs import READERS, fuzz, lzf_compress

from flowslam.datasets.pcd import lzf_decompress
from flowslam.errors import InputError

EXAMPLES = {"kitti_bin": 150, "pcd": 500, "ply": 350, "npy": 300, "pointcloud2": 350,
            "trajectory_tum": 250, "trajectory_kitti": 250}
"""Inputs per reader in CI."""

@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@pytest.mark.parametrize("reader", sorted(READERS))
def test_reader_answers_valid_or_one_line_input_error(reader, folder):
    tried = fuzz(reader, folder, EXAMPLES[reader])
    outcomes = {k[1]: v for k, v in fuzz_inputs.OUTCOMES.items() if k[0] == reader}
    print(f"\nfuzz {reader}: {tried} inputs tried, outcomes {outcomes}")
    assert tried >= EXAMPLES[reader] // 2  # Hypothesis stops early only when it runs out of new inputs
    assert outcomes.get("valid", 0) and outcomes.get("InputError", 0)  # both answers were exercised


def test_lzf_round_trip_and_corruption(tmp_path):
    rng = np.random.default_rng(0)
    for data in (b"", b"a", b"abcabcabcabcabcabc" * 50, rng.normal(size=500).astype("<f4").tobytes(),
                 bytes(1000)):
        assert lzf_decompress(lzf_compress(data), len(data), tmp_path) == data
    packed = lzf_compress(b"abcabcabcabcabcabc" * 50)
    for bad, size in ((packed[:-1], 900), (packed, 899), (packed, 901), (bytes([0xE0, 0xFF, 0x00]), 10)):
        with pytest.raises(InputError, match="binary_compressed data"):
            lzf_decompress(bad, size, tmp_path)


def test_our_compressed_pcd_is_what_open3d_reads(tmp_path):
    """The fuzz generator's LZF and layout are PCL's: Open3D reads the files it writes."""
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(1).normal(0, 10, (300, 3)).astype(np.float32)
    layout = [("x", "f4", 1), ("y", "f4", 1), ("z", "f4", 1), ("intensity", "f4", 1)]
    data, _ = fuzz_inputs.pcd_bytes(pts, np.linspace(0, 1, 300, dtype=np.float32), layout, "binary_compressed", 1)
    assert struct.unpack_from("<II", data, data.index(b"DATA binary_compressed\n") + 23)[1] == 300 * 16
    (tmp_path / "c.pcd").write_bytes(data)
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "c.pcd"))
    np.testing.assert_array_equal(cloud.point.positions.numpy(), pts)
