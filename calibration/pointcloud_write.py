"""Point-cloud files written: PCD v0.7 (ascii, binary, binary_compressed) and PLY (ascii, binary
little-endian), from 1-D fields; calibration.pointcloud_io reads them back."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.pointcloud_io import lzf_store


def write_pcd(path: str | Path, fields: dict[str, np.ndarray], mode: str = "binary") -> None:
    """Write 1-D fields (float32/float64/int/uint) as PCD v0.7; mode ascii|binary|binary_compressed."""
    names = list(fields)
    arrays = [np.ascontiguousarray(fields[k]) for k in names]
    n = len(arrays[0])
    kinds = {"f": "F", "i": "I", "u": "U"}
    header = [
        "# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(str(a.dtype.itemsize) for a in arrays),
        "TYPE " + " ".join(kinds[a.dtype.kind] for a in arrays),
        "COUNT " + " ".join("1" for _ in arrays),
        f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}", f"DATA {mode}",
    ]
    head = ("\n".join(header) + "\n").encode("ascii")
    if mode == "ascii":
        body = "\n".join(" ".join(repr(a[i].item()) for a in arrays) for i in range(n)).encode() + b"\n"
    elif mode == "binary":
        dtype = np.dtype([(k, a.dtype.newbyteorder("<")) for k, a in zip(names, arrays)])
        rec = np.empty(n, dtype=dtype)
        for k, a in zip(names, arrays):
            rec[k] = a
        body = rec.tobytes()
    elif mode == "binary_compressed":
        raw = b"".join(a.astype(a.dtype.newbyteorder("<")).tobytes() for a in arrays)
        comp = lzf_store(raw)
        body = np.array([len(comp), len(raw)], dtype="<u4").tobytes() + comp
    else:
        raise ValueError(f"unknown PCD mode {mode!r}")
    Path(path).write_bytes(head + body)


def write_ply(path: str | Path, fields: dict[str, np.ndarray], binary: bool = True) -> None:
    """Write 1-D fields as a PLY vertex element (binary little-endian or ascii)."""
    inv = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
           "f4": "float", "f8": "double"}
    names = list(fields)
    arrays = [np.ascontiguousarray(fields[k]) for k in names]
    n = len(arrays[0])
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", f"element vertex {n}"]
    header += [f"property {inv[a.dtype.str[1:]]} {k}" for k, a in zip(names, arrays)]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    if binary:
        rec = np.empty(n, dtype=np.dtype([(k, a.dtype.newbyteorder("<")) for k, a in zip(names, arrays)]))
        for k, a in zip(names, arrays):
            rec[k] = a
        body = rec.tobytes()
    else:
        body = "".join(" ".join(repr(a[i].item()) for a in arrays) + "\n" for i in range(n)).encode()
    Path(path).write_bytes(head + body)
