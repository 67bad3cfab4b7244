"""Point-cloud files: PCD (ascii, binary, binary_compressed) and PLY (ascii, binary LE/BE), read.

`load_point_cloud(path)` returns a `PointCloud` (named per-point fields plus an (N,3) `xyz`).
Any malformed file raises `PointCloudFormatError` naming the file and what is wrong; nothing
else escapes the parsers (they are fuzzed with arbitrary bytes in the tests). Writing them:
calibration.pointcloud_write.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAX_POINTS = 50_000_000  # a larger header claim is treated as corrupt, not allocated


class PointCloudFormatError(ValueError):
    """A point-cloud file is malformed, truncated or uses an unsupported feature."""


@dataclass
class PointCloud:
    """Per-point fields by name (each (N,) or (N, count)); `xyz` is (N,3) float64."""

    fields: dict[str, np.ndarray]

    @property
    def xyz(self) -> np.ndarray:
        return np.stack([self.fields[k] for k in ("x", "y", "z")], axis=1).astype(np.float64)

    def __len__(self) -> int:
        return len(self.fields["x"])


def finite_xyz(cloud: PointCloud, where: str) -> np.ndarray:
    """The cloud's points with finite x, y, z as (M,3) float64, for a command that needs points.

    An empty cloud, or one whose points are all NaN/inf, raises PointCloudFormatError naming
    `where` (the file) and the counts.
    """
    xyz = cloud.xyz
    if len(xyz) == 0:
        raise PointCloudFormatError(f"{where}: the point cloud is empty (0 points)")
    finite = xyz[np.isfinite(xyz).all(axis=1)]
    if len(finite) == 0:
        raise PointCloudFormatError(f"{where}: none of its {len(xyz)} points has finite x, y, z (all NaN or inf)")
    return finite


# ---------------------------------------------------------------------------- helpers
def _fail(where: str, msg: str) -> PointCloudFormatError:
    return PointCloudFormatError(f"{where}: {msg}")


def _check_xyz(fields: dict[str, np.ndarray], where: str) -> PointCloud:
    missing = [k for k in ("x", "y", "z") if k not in fields]
    if missing:
        raise _fail(where, f"no {'/'.join(missing)} field (fields: {list(fields)})")
    for k in ("x", "y", "z"):
        if fields[k].ndim != 1:
            raise _fail(where, f"field {k} must have count 1")
    return PointCloud(fields)


def _read_header_lines(data: bytes, where: str, end_keyword: bytes, max_lines: int = 200) -> tuple[list[str], int]:
    """Split header lines up to and including the line starting with end_keyword."""
    lines: list[str] = []
    pos = 0
    for _ in range(max_lines):
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise _fail(where, f"header ends before the '{end_keyword.decode()}' line")
        raw = data[pos:nl].rstrip(b"\r")
        pos = nl + 1
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise _fail(where, f"header line {len(lines) + 1} is not ASCII text") from None
        lines.append(line)
        if line.split(" ", 1)[0] == end_keyword.decode():
            return lines, pos
    raise _fail(where, f"no '{end_keyword.decode()}' line in the first {max_lines} header lines")


def _parse_int(text: str, where: str, what: str, lo: int = 0, hi: int = MAX_POINTS) -> int:
    try:
        v = int(text)
    except ValueError:
        raise _fail(where, f"{what} is not an integer: {text!r}") from None
    if not lo <= v <= hi:
        raise _fail(where, f"{what} = {v} is out of range [{lo}, {hi}]")
    return v


def _ascii_table(body: bytes, n_rows: int, n_cols: int, where: str, exact: bool = False) -> np.ndarray:
    """The first n_rows data rows as floats; exact: no further rows may follow (PCD)."""
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise _fail(where, "ascii data section contains non-ASCII bytes") from None
    rows = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(rows) < n_rows or (exact and len(rows) > n_rows):
        raise _fail(where, f"ascii data has {len(rows)} rows, header says {n_rows} points")
    rows = rows[:n_rows]
    for i, r in enumerate(rows):
        if len(r) != n_cols:
            raise _fail(where, f"ascii data row {i} has {len(r)} values, expected {n_cols}")
    try:
        return np.array(rows, dtype=np.float64).reshape(n_rows, n_cols)
    except ValueError as exc:
        raise _fail(where, f"ascii data has a value that is not a number ({exc})") from None


# ---------------------------------------------------------------------------- PCD
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


#: LZF cannot expand data more than 88x (its longest back reference, 3 bytes, yields 264 bytes);
#: a binary_compressed header announcing more than this ratio is corrupt and is refused before
#: the output is allocated.
MAX_LZF_EXPANSION = 100

_LZF_ERRORS = {
    -1: "literal run past the end of the compressed data",
    -2: "literal run past the end of the output",
    -3: "truncated back reference",
    -4: "back reference before the start of the output",
    -5: "back reference past the end of the output",
}


def _lzf_kernel_source(src, out):  # pragma: no cover - runs compiled by numba
    """LibLZF's lzf_decompress (liblzf 3.6 lzf_d.c) over uint8 arrays.

    Returns the number of bytes written, or a negative code from _LZF_ERRORS. numba compiles it
    (docs/decisions/io-lzf-decoder.md).
    """
    ip = 0
    op = 0
    n = src.shape[0]
    out_len = out.shape[0]
    while ip < n:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n:
                return -1
            if op + length > out_len:
                return -2
            for k in range(length):
                out[op + k] = src[ip + k]
            ip += length
            op += length
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    return -3
                length += np.int64(src[ip])
                ip += 1
            if ip >= n:
                return -3
            ref = op - ((ctrl & 0x1F) << 8) - np.int64(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0:
                return -4
            if op + length > out_len:
                return -5
            for k in range(length):  # may overlap the output being written: byte by byte
                out[op + k] = out[ref + k]
            op += length
    return op


_lzf_kernel = None


def _compiled_lzf_kernel():
    """The numba-compiled LZF kernel (compiled on first use, cached on disk by numba)."""
    global _lzf_kernel
    if _lzf_kernel is None:
        import numba

        _lzf_kernel = numba.njit(cache=True, nogil=True)(_lzf_kernel_source)
    return _lzf_kernel


def lzf_decompress(src: bytes, out_len: int) -> bytes:
    """Decompress LibLZF data (used by PCD binary_compressed); errors raise PointCloudFormatError.

    out_len is the exact decompressed size; it may not exceed MAX_LZF_EXPANSION x len(src).
    """
    if out_len < 0 or out_len > MAX_LZF_EXPANSION * len(src):
        raise PointCloudFormatError(
            f"LZF: {out_len} decompressed bytes announced for {len(src)} compressed bytes "
            f"(LZF expands at most {MAX_LZF_EXPANSION}x)"
        )
    out = np.empty(out_len, dtype=np.uint8)
    written = int(_compiled_lzf_kernel()(np.frombuffer(src, dtype=np.uint8), out))
    if written < 0:
        raise PointCloudFormatError(f"LZF: {_LZF_ERRORS[written]}")
    if written != out_len:
        raise PointCloudFormatError(f"LZF: decompressed {written} bytes, expected {out_len}")
    return out.tobytes()


def lzf_store(data: bytes) -> bytes:
    """A valid LZF stream holding `data` as literal runs only (no compression; for writing)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def parse_pcd(data: bytes, where: str = "<pcd>") -> PointCloud:
    """Parse PCD bytes (v0.6/v0.7; DATA ascii, binary or binary_compressed)."""
    lines, pos = _read_header_lines(data, where, b"DATA")
    layout = _pcd_layout(lines, where)
    mode = layout.mode
    body = data[pos:]
    if mode == "ascii":
        fields = _pcd_ascii(body, layout, where)
    elif mode == "binary":
        fields = _pcd_binary(body, layout, where)
    elif mode == "binary_compressed":
        fields = _pcd_compressed(body, layout, where)
    else:
        raise _fail(where, f"unsupported DATA mode {mode!r} (ascii, binary, binary_compressed)")
    return _check_xyz(fields, where)


@dataclass(frozen=True)
class _PcdLayout:
    """What a PCD header says: the fields (name, numpy type, byte size, count), points, DATA mode."""

    names: list[str]
    dtypes: list[str]
    sizes: list[int]
    counts: list[int]
    n: int
    mode: str


def _pcd_header(lines: list[str]) -> dict[str, list[str]]:
    hdr: dict[str, list[str]] = {}
    for line in lines:
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        hdr[key.upper()] = vals
    return hdr


def _pcd_layout(lines: list[str], where: str) -> _PcdLayout:
    hdr = _pcd_header(lines)
    for key in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if key not in hdr:
            raise _fail(where, f"header has no {key} line")
    names = hdr["FIELDS"]
    n_f = len(names)
    if n_f == 0 or len(set(names)) != n_f:
        raise _fail(where, f"FIELDS must list distinct names, got {names}")
    sizes = [_parse_int(s, where, "SIZE", 1, 8) for s in hdr["SIZE"]]
    types = [t.upper() for t in hdr["TYPE"]]
    counts = [_parse_int(c, where, "COUNT", 1, 1024) for c in hdr.get("COUNT", ["1"] * n_f)]
    if not (len(sizes) == len(types) == len(counts) == n_f):
        raise _fail(where, f"FIELDS ({n_f}), SIZE ({len(sizes)}), TYPE ({len(types)}) and COUNT "
                           f"({len(counts)}) must have the same length")
    dtypes = []
    for name, t, s in zip(names, types, sizes):
        if (t, s) not in _PCD_TYPES:
            raise _fail(where, f"field {name}: unsupported TYPE {t} with SIZE {s}")
        dtypes.append(_PCD_TYPES[(t, s)])
    n = _pcd_points(hdr, where)
    mode = hdr["DATA"][0].lower() if hdr["DATA"] else ""
    return _PcdLayout(names, dtypes, sizes, counts, n, mode)


def _pcd_points(hdr: dict[str, list[str]], where: str) -> int:
    """POINTS (else WIDTH x HEIGHT), checked against WIDTH x HEIGHT when both are given."""
    if "POINTS" in hdr and hdr["POINTS"]:
        n = _parse_int(hdr["POINTS"][0], where, "POINTS")
    elif "WIDTH" in hdr and "HEIGHT" in hdr and hdr["WIDTH"] and hdr["HEIGHT"]:
        n = _parse_int(hdr["WIDTH"][0], where, "WIDTH") * _parse_int(hdr["HEIGHT"][0], where, "HEIGHT")
    else:
        raise _fail(where, "header has neither POINTS nor WIDTH/HEIGHT")
    if n > MAX_POINTS:
        raise _fail(where, f"{n} points is more than the supported {MAX_POINTS}")
    if "WIDTH" in hdr and "HEIGHT" in hdr and hdr["WIDTH"] and hdr["HEIGHT"]:
        w = _parse_int(hdr["WIDTH"][0], where, "WIDTH")
        h = _parse_int(hdr["HEIGHT"][0], where, "HEIGHT")
        if w * h != n:
            raise _fail(where, f"WIDTH*HEIGHT = {w * h} does not match POINTS = {n}")
    return n


def _pcd_ascii(body: bytes, layout: _PcdLayout, where: str) -> dict[str, np.ndarray]:
    n, counts = layout.n, layout.counts
    table = _ascii_table(body, n, sum(counts), where, exact=True)
    fields: dict[str, np.ndarray] = {}
    col = 0
    for name, dt, c in zip(layout.names, layout.dtypes, counts):
        vals = table[:, col:col + c]
        col += c
        if dt.startswith(("i", "u")):
            if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
                raise _fail(where, f"field {name} is an integer field but has non-integer values")
            info = np.iinfo(np.dtype(dt))
            if np.any(vals < info.min) or np.any(vals > info.max):
                raise _fail(where, f"field {name}: value out of range for {dt}")
        arr = vals.astype(dt)
        fields[name] = arr[:, 0] if c == 1 else arr
    return fields


def _pcd_binary(body: bytes, layout: _PcdLayout, where: str) -> dict[str, np.ndarray]:
    names, n = layout.names, layout.n
    dtype = np.dtype([(nm, "<" + dt, (c,) if c > 1 else ()) for nm, dt, c in zip(names, layout.dtypes, layout.counts)])
    need = n * dtype.itemsize
    if len(body) != need:
        raise _fail(where, f"binary data has {len(body)} bytes, header's {n} points x {dtype.itemsize} bytes "
                           f"need {need}")
    rec = np.frombuffer(body, dtype=dtype, count=n)
    return {nm: np.ascontiguousarray(rec[nm]) for nm in names}


def _pcd_compressed(body: bytes, layout: _PcdLayout, where: str) -> dict[str, np.ndarray]:
    n = layout.n
    if len(body) < 8:
        raise _fail(where, "binary_compressed data is shorter than its 8-byte size header")
    comp_size, raw_size = np.frombuffer(body[:8], dtype="<u4")
    comp_size, raw_size = int(comp_size), int(raw_size)
    item_sizes = [s * c for s, c in zip(layout.sizes, layout.counts)]
    if raw_size != n * sum(item_sizes):
        raise _fail(where, f"binary_compressed: uncompressed size {raw_size} does not match "
                           f"{n} points x {sum(item_sizes)} bytes")
    if comp_size != len(body) - 8:
        raise _fail(where, f"binary_compressed: {comp_size} compressed bytes announced, "
                           f"{len(body) - 8} present")
    try:
        raw = lzf_decompress(body[8:8 + comp_size], raw_size)
    except PointCloudFormatError as exc:
        raise _fail(where, f"binary_compressed: {exc}") from None
    fields: dict[str, np.ndarray] = {}
    off = 0  # column-major: all values of field 0, then field 1, ...
    for name, dt, c, isz in zip(layout.names, layout.dtypes, layout.counts, item_sizes):
        arr = np.frombuffer(raw, dtype="<" + dt, count=n * c, offset=off).reshape(n, c)
        off += n * isz
        fields[name] = arr[:, 0].copy() if c == 1 else arr.copy()
    return fields


# ---------------------------------------------------------------------------- PLY
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def parse_ply(data: bytes, where: str = "<ply>") -> PointCloud:
    """Parse PLY bytes: the `vertex` element (scalar properties), which must come first."""
    if not data.startswith(b"ply"):
        raise _fail(where, "does not start with 'ply'")
    lines, pos = _read_header_lines(data, where, b"end_header")
    if lines[0] != "ply":
        raise _fail(where, "first line must be exactly 'ply'")
    fmt, elements = _ply_header(lines[1:-1], where)
    if fmt is None:
        raise _fail(where, "header has no format line")
    if not elements or elements[0][0] != "vertex":
        raise _fail(where, "the first element must be 'vertex'")
    _, n, props = elements[0]
    if any(t == "list" for _, t in props):
        raise _fail(where, "list properties in the vertex element are not supported")
    names = [p for p, _ in props]
    if len(set(names)) != len(names) or not names:
        raise _fail(where, f"vertex properties must be distinct and non-empty, got {names}")
    body = data[pos:]
    if fmt == "ascii":
        fields = _ply_ascii(body, n, props, where)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(nm, order + dt) for nm, dt in props])
        need = n * dtype.itemsize
        if len(body) < need:
            raise _fail(where, f"binary vertex data has {len(body)} bytes, {n} vertices need {need}")
        rec = np.frombuffer(body, dtype=dtype, count=n)
        fields = {nm: rec[nm].astype(rec[nm].dtype.newbyteorder("=")) for nm in names}
    return _check_xyz(fields, where)


def _ply_header(lines: list[str], where: str) -> tuple[str | None, list[tuple[str, int, list[tuple[str, str]]]]]:
    """The format and the elements (name, count, [(property, numpy type or "list")]) of the
    header lines between 'ply' and 'end_header'."""
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) != 3 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _fail(where, f"unsupported format line {line!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3:
                raise _fail(where, f"bad element line {line!r}")
            elements.append((parts[1], _parse_int(parts[2], where, f"element {parts[1]} count"), []))
        elif parts[0] == "property":
            if not elements:
                raise _fail(where, "property before any element")
            if len(parts) >= 2 and parts[1] == "list":
                elements[-1][2].append(("list", "list"))
                continue
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise _fail(where, f"bad property line {line!r}")
            elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
        else:
            raise _fail(where, f"unknown header line {line!r}")
    return fmt, elements


def _ply_ascii(body: bytes, n: int, props: list[tuple[str, str]], where: str) -> dict[str, np.ndarray]:
    table = _ascii_table(body, n, len(props), where)
    fields = {}
    for i, (nm, dt) in enumerate(props):
        vals = table[:, i]
        if dt.startswith(("i", "u")):
            if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
                raise _fail(where, f"property {nm} is an integer but has non-integer values")
            info = np.iinfo(np.dtype(dt))
            if np.any(vals < info.min) or np.any(vals > info.max):
                raise _fail(where, f"property {nm}: value out of range for {dt}")
        fields[nm] = vals.astype(dt)
    return fields


# ---------------------------------------------------------------------------- entry point
def load_point_cloud(path: str | Path) -> PointCloud:
    """Load a .pcd or .ply file (chosen by its first bytes, else by its suffix)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise PointCloudFormatError(f"{p}: cannot read file: {exc.strerror or exc}") from exc
    return parse_point_cloud(data, where=str(p), suffix=p.suffix.lower())


def parse_point_cloud(data: bytes, where: str = "<bytes>", suffix: str = "") -> PointCloud:
    """Parse PLY or PCD bytes; every failure is a PointCloudFormatError."""
    if data.startswith(b"ply"):
        return parse_ply(data, where)
    if suffix == ".pcd" or data.lstrip().startswith((b"#", b"VERSION", b"FIELDS")):
        return parse_pcd(data, where)
    if suffix == ".ply":
        return parse_ply(data, where)
    raise _fail(where, "neither a PLY nor a PCD file (unknown header)")


__all__ = ["PointCloud", "PointCloudFormatError", "finite_xyz", "MAX_LZF_EXPANSION", "load_point_cloud",
           "parse_point_cloud", "parse_pcd", "parse_ply", "lzf_decompress", "lzf_store"]
