"""Point-cloud loaders: round trips, the real files, malformed input, fuzzing."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.pointcloud_io import (PointCloudFormatError, load_point_cloud, lzf_decompress, parse_pcd,
                                       parse_ply, parse_point_cloud, write_pcd, write_ply)

from .conftest import PANDAR, REAL


def _fields(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "x": rng.normal(size=n).astype(np.float32),
        "y": rng.normal(size=n).astype(np.float32),
        "z": rng.normal(size=n).astype(np.float64),
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "ring": rng.integers(-100, 100, n).astype(np.int8),
    }


def _same(cloud, fields):
    assert list(cloud.fields) == list(fields)
    for k, v in fields.items():
        assert cloud.fields[k].dtype == v.dtype, k
        np.testing.assert_array_equal(cloud.fields[k], v)


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_round_trip(tmp_path, mode):
    f = _fields()
    write_pcd(tmp_path / "a.pcd", f, mode)
    c = load_point_cloud(tmp_path / "a.pcd")
    _same(c, f)
    assert c.xyz.shape == (50, 3)


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path, binary):
    f = _fields()
    write_ply(tmp_path / "a.ply", f, binary)
    _same(load_point_cloud(tmp_path / "a.ply"), f)


def test_ply_big_endian_and_trailing_face_element():
    f = _fields(7)
    rec = np.empty(7, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f8")])
    for k in "xyz":
        rec[k] = f[k]
    head = (b"ply\nformat binary_big_endian 1.0\ncomment t\nelement vertex 7\nproperty float x\nproperty float y\n"
            b"property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
    c = parse_ply(head + rec.tobytes() + b"\x03\x00\x00\x00\x00\x00\x00\x00\x01\x00\x00\x00\x02")
    np.testing.assert_array_equal(c.fields["x"], f["x"])
    np.testing.assert_array_equal(c.fields["z"], f["z"])


def test_lzf_back_reference():
    # literal "abc" then a back reference of length 6 at distance 3 -> "abcabcabc"
    data = bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2])
    assert lzf_decompress(data, 9) == b"abcabcabc"
    with pytest.raises(PointCloudFormatError):
        lzf_decompress(bytes([(4 << 5) | 0, 9]), 6)


def test_real_pandar_pcd():
    c = load_point_cloud(PANDAR / "0.pcd")
    assert len(c) == 78238  # README
    assert list(c.fields) == ["x", "y", "z", "intensity"]
    np.testing.assert_allclose(c.xyz[0], [21.647913, 0.19822195, -1.8524752], rtol=1e-6)


@pytest.mark.parametrize("name,n", [("source.ply", 69792), ("target.ply", 69088)])
def test_real_hdl32_ply(name, n):
    c = load_point_cloud(REAL / "hdl32_pair_small_gicp" / name)
    assert len(c) == n  # README
    xyz = c.xyz
    zero = np.all(xyz == 0, axis=1).sum()
    assert 4000 < zero < 6500  # "about 5.1k points per scan are exactly (0,0,0)"
    r = np.linalg.norm(xyz[~np.all(xyz == 0, axis=1)], axis=1)
    assert 0.5 < np.median(r) < 100


GOOD_PCD = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n"
            b"DATA ascii\n1 2 3\n4 5 6\n")


@pytest.mark.parametrize(
    "data,match",
    [
        (GOOD_PCD.replace(b"4 5 6\n", b""), "rows"),
        (GOOD_PCD.replace(b"4 5 6", b"4 5"), "values"),
        (GOOD_PCD.replace(b"4 5 6", b"4 five 6"), "not a number"),
        (GOOD_PCD.replace(b"FIELDS x y z", b"FIELDS a b c"), "no x/y/z"),
        (GOOD_PCD.replace(b"SIZE 4 4 4", b"SIZE 4 4"), "same length"),
        (GOOD_PCD.replace(b"TYPE F F F", b"TYPE F F Q"), "unsupported TYPE"),
        (GOOD_PCD.replace(b"POINTS 2", b"POINTS 3"), "WIDTH"),
        (GOOD_PCD.replace(b"DATA ascii", b"DATA foo"), "DATA mode"),
        (GOOD_PCD.replace(b"DATA ascii\n1 2 3\n4 5 6\n", b"DATA binary\n" + b"\0" * 20), "bytes"),
        (GOOD_PCD.replace(b"DATA ascii\n1 2 3\n4 5 6\n", b"DATA binary_compressed\n\x05\0\0\0\x18\0\0\0ab"), "compressed"),
        (GOOD_PCD.replace(b"POINTS 2", b"POINTS 999999999999").replace(b"WIDTH 2", b"WIDTH 999999999999"), "range"),
        (GOOD_PCD.split(b"DATA")[0], "header ends"),
    ],
)
def test_malformed_pcd(data, match):
    with pytest.raises(PointCloudFormatError, match=match):
        parse_pcd(data, "t.pcd")


GOOD_PLY = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n" + np.zeros(6, "<f4").tobytes()


@pytest.mark.parametrize(
    "data,match",
    [
        (GOOD_PLY[:-1], "bytes"),
        (GOOD_PLY.replace(b"binary_little_endian", b"binary_middle_endian"), "format"),
        (GOOD_PLY.replace(b"property float z\n", b""), "no z"),
        (GOOD_PLY.replace(b"property float z", b"property quad z"), "property"),
        (GOOD_PLY.replace(b"element vertex 2", b"element vertex -2"), "range"),
        (GOOD_PLY.replace(b"format binary_little_endian 1.0\n", b""), "format"),
        (GOOD_PLY.replace(b"end_header\n", b""), "end_header"),
    ],
)
def test_malformed_ply(data, match):
    with pytest.raises(PointCloudFormatError, match=match):
        parse_ply(data, "t.ply")


def test_missing_file_is_named(tmp_path):
    with pytest.raises(PointCloudFormatError, match="nope.pcd"):
        load_point_cloud(tmp_path / "nope.pcd")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600), st.sampled_from(["", ".pcd", ".ply"]))
def test_fuzz_arbitrary_bytes(data, suffix):
    try:
        parse_point_cloud(data, "fuzz", suffix)
    except PointCloudFormatError:
        pass


_header_line = st.sampled_from([
    b"VERSION 0.7", b"FIELDS x y z", b"FIELDS x y z i", b"SIZE 4 4 4", b"SIZE 4 4 4 1", b"SIZE 8 4 2",
    b"TYPE F F F", b"TYPE F F F U", b"TYPE I U F", b"COUNT 1 1 1", b"COUNT 1 1 1 1", b"COUNT 2 1 1", b"WIDTH 2",
    b"WIDTH 0", b"HEIGHT 1", b"POINTS 2", b"POINTS 1", b"DATA ascii", b"DATA binary", b"DATA binary_compressed",
])


@settings(max_examples=400, deadline=None)
@given(st.lists(_header_line, max_size=10), st.binary(max_size=80),
       st.lists(st.sampled_from([b"1 2 3", b"1 2 3 4", b"nan inf -1", b"1e400 0 0", b"a b"]), max_size=3))
def test_fuzz_structured_pcd(lines, body, rows):
    data = b"\n".join(lines) + b"\nDATA " + (b"ascii\n" + b"\n".join(rows) if rows else b"binary\n" + body)
    try:
        parse_pcd(data, "fuzz")
    except PointCloudFormatError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from([
    b"format binary_little_endian 1.0", b"format ascii 1.0", b"format binary_big_endian 1.0", b"element vertex 1",
    b"element vertex 3", b"element face 2", b"property float x", b"property float y", b"property double z",
    b"property uchar z", b"property list uchar int vertex_indices", b"comment hi"]), max_size=8),
    st.binary(max_size=60))
def test_fuzz_structured_ply(lines, body):
    data = b"ply\n" + b"\n".join(lines) + b"\nend_header\n" + body
    try:
        parse_ply(data, "fuzz")
    except PointCloudFormatError:
        pass
