"""Point-cloud loaders: round trips, the real files, malformed input, fuzzing."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.pointcloud_io import (PointCloudFormatError, load_point_cloud, lzf_decompress, parse_pcd,
                                       parse_ply, parse_point_cloud)
from calibration.pointcloud_write import write_pcd, write_ply

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


# ---------------------------------------------------------------------------- LZF (numba) and header/body checks
def _lzf_reference(src: bytes, out_len: int) -> bytes:
    """liblzf's lzf_decompress as a plain Python loop: the oracle for the compiled decoder."""
    out = bytearray(out_len)
    ip = op = 0
    while ip < len(src):
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > len(src) or op + length > out_len:
                raise ValueError("literal")
            out[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= len(src):
                    raise ValueError("truncated")
                length += src[ip]
                ip += 1
            if ip >= len(src):
                raise ValueError("truncated")
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > out_len:
                raise ValueError("reference")
            for _ in range(length):
                out[op] = out[ref]
                op += 1
                ref += 1
    if op != out_len:
        raise ValueError("short")
    return bytes(out)


def _lzf_compress(data: bytes) -> bytes:
    """A greedy LZF compressor (liblzf's format: literal runs <= 32, back references 3..264 at <= 8192)."""
    out, lit, last = bytearray(), bytearray(), {}
    i = 0

    def flush():
        for k in range(0, len(lit), 32):
            chunk = lit[k:k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        lit.clear()

    while i < len(data):
        best_len, best_off = 0, 0
        for j in last.get(data[i:i + 3], [])[-16:]:
            if i - j > 8192:
                continue
            n = 0
            while i + n < len(data) and n < 264 and data[j + n] == data[i + n]:
                n += 1
            if n > best_len:
                best_len, best_off = n, i - j - 1
        if best_len >= 3:
            flush()
            L = best_len - 2
            if L < 7:
                out += bytes([(L << 5) | (best_off >> 8), best_off & 0xFF])
            else:
                out += bytes([(7 << 5) | (best_off >> 8), L - 7, best_off & 0xFF])
            for k in range(best_len):
                last.setdefault(data[i + k:i + k + 3], []).append(i + k)
            i += best_len
        else:
            last.setdefault(data[i:i + 3], []).append(i)
            lit.append(data[i])
            i += 1
    flush()
    return bytes(out)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 3000))
def test_lzf_decoder_agrees_with_the_reference_on_any_input(src, out_len):
    out_len = min(out_len, 100 * len(src))
    try:
        expected = _lzf_reference(src, out_len)
    except ValueError:
        with pytest.raises(PointCloudFormatError, match="LZF"):
            lzf_decompress(src, out_len)
    else:
        assert lzf_decompress(src, out_len) == expected


@settings(max_examples=100, deadline=None)
@given(st.lists(st.sampled_from([b"ab", b"abcabc", b"\x00" * 40, b"xyz" * 100, b"\x01\x02\x03\x04"]), max_size=30),
       st.binary(max_size=50))
def test_lzf_round_trip_with_back_references(pieces, tail):
    data = b"".join(pieces) + tail
    comp = _lzf_compress(data)
    assert lzf_decompress(comp, len(data)) == data


def _compressed_pcd(fields: dict, raw_size: int | None = None, trailing: bytes = b"") -> bytes:
    n = len(fields["x"])
    raw = b"".join(np.ascontiguousarray(a).astype("<f4").tobytes() for a in fields.values())
    comp = _lzf_compress(raw)
    head = (f"VERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join('4' for _ in fields)}\n"
            f"TYPE {' '.join('F' for _ in fields)}\nCOUNT {' '.join('1' for _ in fields)}\nWIDTH {n}\nHEIGHT 1\n"
            f"POINTS {n}\nDATA binary_compressed\n").encode()
    sizes = np.array([len(comp), len(raw) if raw_size is None else raw_size], dtype="<u4").tobytes()
    return head + sizes + comp + trailing


def test_binary_compressed_pcd_with_real_compression():
    xyz = np.zeros((500, 3), np.float32)
    xyz[::7] = [1.0, 2.0, 3.0]  # repetitive: compresses with back references
    fields = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    data = _compressed_pcd(fields)
    assert len(data) < 500 * 12 / 4
    np.testing.assert_array_equal(parse_pcd(data, "t.pcd").xyz, xyz)


def test_lzf_expansion_cap_refused_before_allocating():
    # 1e6 points x 12 bytes announced for 16 compressed bytes: consistent with POINTS but 750000x.
    head = (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000\nHEIGHT 1\n"
            b"POINTS 1000000\nDATA binary_compressed\n")
    data = head + np.array([16, 12_000_000], dtype="<u4").tobytes() + bytes([31]) + b"\0" * 15
    with pytest.raises(PointCloudFormatError, match=r"t\.pcd: .*12000000 decompressed bytes .* 16 compressed .*100x"):
        parse_pcd(data, "t.pcd")
    with pytest.raises(PointCloudFormatError, match="at most"):
        lzf_decompress(b"\x00a", 201)


@pytest.mark.parametrize(
    "data,numbers",
    [
        (GOOD_PCD + b"7 8 9\n", ("3 rows", "2 points")),
        (GOOD_PCD.replace(b"DATA ascii\n1 2 3\n4 5 6\n", b"DATA binary\n" + b"\0" * 28), ("28 bytes", "need 24")),
        (GOOD_PCD.replace(b"DATA ascii\n1 2 3\n4 5 6\n", b"DATA binary\n" + b"\0" * 20), ("20 bytes", "need 24")),
    ],
)
def test_header_and_body_disagree_in_either_direction(tmp_path, data, numbers):
    path = tmp_path / "scan.pcd"
    path.write_bytes(data)
    with pytest.raises(PointCloudFormatError) as err:
        load_point_cloud(path)
    msg = str(err.value)
    assert str(path) in msg and all(n in msg for n in numbers), msg


def test_compressed_body_longer_than_announced():
    f = _fields(20)
    data = _compressed_pcd({"x": f["x"], "y": f["y"], "z": f["z"].astype(np.float32)}, trailing=b"junk")
    with pytest.raises(PointCloudFormatError, match="compressed bytes announced"):
        parse_pcd(data, "t.pcd")


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 12), st.sampled_from(["ascii", "binary", "binary_compressed"]),
       st.integers(-30, 30).filter(lambda d: d != 0), st.sampled_from(["body", "points"]))
def test_fuzz_header_body_mismatch_is_always_named(n, mode, delta, where):
    """Any disagreement between the header's point count and the body raises the reader's error."""
    import tempfile
    from pathlib import Path

    f = {k: v[:n] for k, v in _fields(12).items() if k in ("x", "y", "z")}
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "a.pcd"
        write_pcd(p, f, mode)
        data = p.read_bytes()
    head, body = data.split(b"DATA " + mode.encode() + b"\n", 1)
    if where == "points":
        m = max(n + delta, 0)
        if m == n:
            return
        head = head.replace(f"WIDTH {n}\n".encode(), f"WIDTH {m}\n".encode()).replace(
            f"POINTS {n}\n".encode(), f"POINTS {m}\n".encode())
    elif mode == "ascii":
        rows = body.decode().splitlines() if n else []
        body = ("\n".join(rows + ["0.5 0.5 0.5"] * delta if delta > 0 else rows[:delta]) + "\n").encode()
        if delta < 0 and n == 0:
            return
    else:
        cut = body + b"\x07" * delta if delta > 0 else body[:delta]
        if cut == body:  # nothing to cut from an empty body
            return
        body = cut
    with pytest.raises(PointCloudFormatError):
        parse_pcd(head + b"DATA " + mode.encode() + b"\n" + body, "fuzz.pcd")


def test_finite_xyz_refuses_empty_and_all_nan_clouds(tmp_path):
    from calibration.pointcloud_io import finite_xyz

    empty = {k: np.zeros(0, np.float32) for k in "xyz"}
    write_pcd(tmp_path / "empty.pcd", empty)
    with pytest.raises(PointCloudFormatError, match=r"empty\.pcd: the point cloud is empty \(0 points\)"):
        finite_xyz(load_point_cloud(tmp_path / "empty.pcd"), str(tmp_path / "empty.pcd"))
    nan = {k: np.full(5, np.nan, np.float32) for k in "xyz"}
    write_pcd(tmp_path / "nan.pcd", nan, "binary_compressed")
    with pytest.raises(PointCloudFormatError, match=r"nan\.pcd: none of its 5 points has finite x, y, z"):
        finite_xyz(load_point_cloud(tmp_path / "nan.pcd"), str(tmp_path / "nan.pcd"))
    some = {k: np.array([np.nan, 1.0], np.float32) for k in "xyz"}
    write_pcd(tmp_path / "some.pcd", some)
    assert finite_xyz(load_point_cloud(tmp_path / "some.pcd"), "some.pcd").shape == (1, 3)
