"""The partition's input checks: every array and transform it is handed, named in the error."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numba import njit

from calibration.camera_model import CameraModel
from runtime.vpp.partition.labels import MAX_COST

MAX_MASKS = 255  # the mask index is packed into 8 bits of the cluster cell key (clustering.py)
_EYE3 = np.eye(3)


class PartitionInputError(ValueError):
    """Bad input to the partition (the message names the field)."""



def fail(field: str, msg: str) -> PartitionInputError:
    return PartitionInputError(f"{field}: {msg}")


def check_points(points: np.ndarray, field: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise fail(field, f"must be an (N, 3) array, got shape {p.shape}")
    if p.dtype.kind != "f":
        raise fail(field, f"must be floating point, got {p.dtype}")
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)  # (keeps NaN and inf)
    p = np.ascontiguousarray(p)  # one numba specialization per dtype, none per memory layout
    bad = nonfinite_rows(p)  # (numba: np.isfinite(p).all() costs a 60 kB temporary)
    if bad:
        raise fail(field, f"{bad} points are not finite (NaN or inf); drop them before the partition")
    return p


@njit(cache=True, nogil=True)
def nonfinite_rows(p):  # pragma: no cover - compiled
    """Number of rows of p (N, 3) with a NaN or an infinite coordinate."""
    bad = 0
    for i in range(p.shape[0]):
        bad += not (np.isfinite(p[i, 0]) and np.isfinite(p[i, 1]) and np.isfinite(p[i, 2]))
    return bad



def check_transform(T: np.ndarray, field: str, known: dict | None = None) -> np.ndarray:
    """T as a new float64 (4, 4) C-contiguous writable array if rigid, else PartitionInputError
    naming `field`. known: transforms (by their bytes) that passed before, checked no more (the
    mounts are the same every scan). Always a fresh array of one type: the compiled kernels take
    the transforms as arguments, and a read-only one (a calibration's) would be another signature
    to compile, in the tick that first meets it."""
    T = np.array(T, dtype=np.float64, order="C")
    if T.shape != (4, 4):
        raise fail(field, f"must be 4x4, got shape {T.shape}")
    key = T.tobytes() if known is not None else None
    if key is not None and key in known:
        return T
    if not np.isfinite(T).all():
        raise fail(field, "is not finite")
    R = T[:3, :3]
    # explicit checks, not np.allclose (too slow for three calls a scan: docs/decisions/vpp-compiled-kernels.md)
    if T[3, 0] != 0.0 or T[3, 1] != 0.0 or T[3, 2] != 0.0 or T[3, 3] != 1.0 \
            or float(np.abs(R @ R.T - _EYE3).max()) > 1e-5 or np.linalg.det(R) < 0:
        raise fail(field, "is not a rigid transform (rotation not orthonormal or last row not [0, 0, 0, 1])")
    if key is not None:
        if len(known) >= 8:
            known.clear()
        known[key] = True
    return T


def stack_masks(masks: np.ndarray | Sequence[np.ndarray], camera: CameraModel) -> np.ndarray:
    """Masks as one C-contiguous (M, H, W) bool array matching the camera (checked).

    Pass an (M, H, W) bool array to avoid the copy that stacking a list costs (~0.3 ms for 8
    masks of 640x480)."""
    H, W = camera.height_px, camera.width_px
    if isinstance(masks, np.ndarray):
        m = masks
        if m.ndim != 3:
            raise fail("masks", f"must be (M, H, W), got shape {m.shape}")
    else:
        masks = list(masks)
        if not masks:
            return np.zeros((0, H, W), dtype=bool)
        shapes = {np.shape(x) for x in masks}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise fail("masks", f"each mask must be (H, W) and all the same size, got shapes {sorted(shapes)}")
        m = np.stack([np.asarray(x) for x in masks])
    if m.dtype != np.bool_:
        raise fail("masks", f"must be bool, got {m.dtype}")
    if m.shape[1:] != (H, W):
        raise fail("masks", f"size {m.shape[2]}x{m.shape[1]} (WxH) does not match the camera {W}x{H}")
    if m.shape[0] > MAX_MASKS:
        raise fail("masks", f"at most {MAX_MASKS} masks, got {m.shape[0]}")
    return np.ascontiguousarray(m)


def check_ids_costs(object_ids, costs, m: int) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(object_ids)
    if ids.shape != (m,) or (m and ids.dtype.kind not in "iu"):
        raise fail("object_ids", f"must be {m} integers (one per mask), got shape {ids.shape} dtype {ids.dtype}")
    ids = ids.astype(np.int32)
    if m and (ids.min() < 0 or len(np.unique(ids)) != m):
        raise fail("object_ids", f"must be distinct and >= 0, got {ids.tolist()}")
    c = np.asarray(costs, dtype=np.float64)
    if c.shape != (m,):
        raise fail("costs", f"must be {m} values (one per mask), got shape {c.shape}")
    if m and not (np.isfinite(c).all() and c.min() >= 0.0 and c.max() <= MAX_COST):
        raise fail("costs", f"must be finite in [0, {MAX_COST}], got {c.tolist()}")
    return ids, c



__all__ = ["MAX_MASKS", "PartitionInputError", "check_ids_costs", "check_points", "check_transform", "fail",
           "stack_masks"]
