"""Integrity record of a distance-net artifact: weight checksum, probe set, error bound.

Written into the artifact's metadata by `save_artifact` and checked by `DistanceNet.load`, so
that a net whose weights changed (a flipped bit, a hand edit, a copy gone wrong), whose weights
are not finite, or that no longer computes what it computed when it was saved (another torch,
edited code), or whose stated accuracy is not true, is refused before the controller uses it.

Weight checksum (`weights_sha256`): sha256 over every tensor of the frozen TorchScript module,
in a fixed order: first the graph's tensor constants in the order the forward uses them (the
names c0, c1, ... that TorchScript prints, `module.code_with_constants`), then any parameters
and buffers by name (a frozen module has none). For each tensor the hash takes the line
"name:dtype:shape;" and then its bytes (C order, little-endian). Any change to any weight, its
shape, or the order in which the forward uses the weights changes the checksum; it is
recomputed from the module as loaded, so it does not depend on how the zip archive is laid out.

Probe set (rule `PROBE_RULE`): a few hundred points around and inside the footprint rectangle,
generated from the footprint's half extents by `probe_points` (documented there). At save time
the record stores the net's mu and distance there (`DistanceNet.dual`, float64) and the exact
distance. At load the net is run on the same points and must reproduce the stored mu and
distance within `PROBE_OUTPUT_TOLERANCE` (the same computation: only float rounding of another
CPU or torch build may differ) and the exact distance within the stored error bound.

Error bound: per region (outside / inside the footprint), the larger of the held-out check's
maximum absolute error (metadata "error_statistics": max_abs_error_m outside,
inside_max_abs_error_m inside) and the largest error on the probe set at save time, plus
`ERROR_BOUND_MARGIN_M`. Outside the footprint the net must also never overestimate the
distance (weak duality) by more than `OVERESTIMATE_TOLERANCE_M`.
"""
from __future__ import annotations

import hashlib
import math
from typing import Any, Callable

import numpy as np

from models.footprint_dual import exact_dual

CHECKSUM_RULE = (
    "sha256 over the frozen module's tensor constants in the order the forward uses them "
    "(code_with_constants c0, c1, ...), then parameters and buffers by name; per tensor "
    "'name:dtype:shape;' then its C-order little-endian bytes"
)
PROBE_RULE = "rectangle-perimeter-offsets-v1"
# Outward offsets (m) of the outside probes from the footprint boundary (the held-out check
# covers 0 to 3 m outside, so every probe lies in the domain its error bound was measured on).
PROBE_OUTSIDE_OFFSETS_M = (1e-3, 1e-2, 5e-2, 0.2, 0.5, 1.0, 2.0, 3.0)
# Inward offsets (m) of the near-boundary inside probes.
PROBE_INSIDE_OFFSETS_M = (1e-3, 1e-2)
# Points per edge on the boundary (the first at the edge's starting corner).
PROBE_POINTS_PER_EDGE = 8
# Interior grid (along x, along y); odd counts put one point at the centre.
PROBE_INTERIOR_GRID = (7, 5)
# Points on each half-diagonal of the inside medial axis.
PROBE_MEDIAL_AXIS_POINTS = 5
# Stored outputs against recomputed ones: mu (dimensionless, ||G^T mu|| <= 1) and distance (m).
PROBE_OUTPUT_TOLERANCE = 1e-5
# Stored exact distances against recomputed ones (m; the stored values are rounded to 1e-10).
EXACT_DISTANCE_TOLERANCE_M = 1e-8
# Margin (m) added to the measured maximum error to make the stored bound.
ERROR_BOUND_MARGIN_M = 1e-4
# The net's distance may exceed the exact one outside by float rounding only.
OVERESTIMATE_TOLERANCE_M = 1e-9
# Digits kept for the stored probe values (far below the tolerances above).
STORED_DECIMALS = 10
# A probe record with fewer points than this is refused (it would check almost nothing).
MIN_PROBE_POINTS = 100

DualFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


class IntegrityError(ValueError):
    """The artifact's integrity check failed; the message says which check and where."""


def weight_tensors(module: Any) -> list[tuple[str, Any]]:
    """(name, tensor) of every weight of a TorchScript module, in the checksum's order."""
    _, constants = module.code_with_constants
    mapping = constants.const_mapping
    ordered = sorted(mapping, key=lambda name: (len(name), name))  # c0, c1, ..., c9, c10, ...
    tensors = [(f"constant:{name}", mapping[name]) for name in ordered]
    tensors += sorted((f"parameter:{n}", t) for n, t in module.named_parameters())
    tensors += sorted((f"buffer:{n}", t) for n, t in module.named_buffers())
    return tensors


def _tensor_bytes(tensor: Any) -> bytes:
    array = tensor.detach().cpu().contiguous().numpy()
    return np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<")).tobytes()


def weights_checksum(tensors: list[tuple[str, Any]]) -> str:
    """sha256 (hex) of the weights as `weight_tensors` lists them (rule: CHECKSUM_RULE)."""
    digest = hashlib.sha256()
    for name, tensor in tensors:
        digest.update(f"{name}:{tensor.dtype}:{tuple(tensor.shape)};".encode())
        digest.update(_tensor_bytes(tensor))
    return digest.hexdigest()


def nonfinite_weights(tensors: list[tuple[str, Any]]) -> list[str]:
    """Names (with the count) of the floating-point weights that hold NaN or inf."""
    import torch

    bad = []
    for name, tensor in tensors:
        if tensor.is_floating_point():
            n_bad = int((~torch.isfinite(tensor)).sum())
            if n_bad:
                bad.append(f"{name} {tuple(tensor.shape)} has {n_bad} non-finite value(s)")
    return bad


def probe_points(half_length_m: float, half_width_m: float) -> np.ndarray:
    """The fixed probe set (N, 2) for a centred rectangle (rule PROBE_RULE), in this order:

    1. outside: on each edge (counter-clockwise, starting at its first corner) PROBE_POINTS_PER_EDGE
       boundary points at fractions k / PROBE_POINTS_PER_EDGE, pushed out by each of
       PROBE_OUTSIDE_OFFSETS_M along the edge normal (at a corner: along the diagonal, and also
       at 22.5 and 67.5 degrees inside the corner's normal cone);
    2. inside: the same boundary points except the corners, pushed in by PROBE_INSIDE_OFFSETS_M;
    3. inside: a PROBE_INTERIOR_GRID grid at the cell centres of the rectangle (the centre included);
    4. inside: PROBE_MEDIAL_AXIS_POINTS on each half-diagonal of the medial axis (where the
       nearest edge switches), at fractions (k + 0.5) / PROBE_MEDIAL_AXIS_POINTS of its length.
    """
    hl, hw = float(half_length_m), float(half_width_m)
    outside, near_inside = _boundary_probes(hl, hw)
    return np.vstack([outside, near_inside, _interior_grid(hl, hw), _medial_axis_probes(hl, hw)])


def _boundary_probes(hl: float, hw: float) -> tuple[np.ndarray, np.ndarray]:
    """(outside, near-inside) probes from points on the boundary (rules 1 and 2 of probe_points)."""
    corners = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])  # edge k starts at corner k
    normals = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    corner_angles = (math.pi / 8, math.pi / 4, 3 * math.pi / 8)
    outside, near_inside = [], []
    for k in range(4):
        start, end, normal = corners[k], corners[(k + 1) % 4], normals[k]
        for i in range(PROBE_POINTS_PER_EDGE):
            point = start + (end - start) * i / PROBE_POINTS_PER_EDGE
            if i == 0:  # the corner: directions in the cone between the previous edge's normal and this one's
                directions = [math.cos(a) * normals[(k - 1) % 4] + math.sin(a) * normal for a in corner_angles]
            else:
                directions = [normal]
                near_inside += [point - d * normal for d in PROBE_INSIDE_OFFSETS_M]
            outside += [point + d * u for u in directions for d in PROBE_OUTSIDE_OFFSETS_M]
    return np.array(outside), np.array(near_inside)


def _interior_grid(hl: float, hw: float) -> np.ndarray:
    """Cell centres of a PROBE_INTERIOR_GRID grid over the rectangle (rule 3)."""
    nx, ny = PROBE_INTERIOR_GRID
    gx = ((np.arange(nx) + 0.5) / nx * 2.0 - 1.0) * hl
    gy = ((np.arange(ny) + 0.5) / ny * 2.0 - 1.0) * hw
    return np.array([[x, y] for x in gx for y in gy])


def _medial_axis_probes(hl: float, hw: float) -> np.ndarray:
    """Points on the four half-diagonals of the inside medial axis (rule 4)."""
    # First quadrant: from (hl - hw, 0) to the corner (for hl >= hw; else from (0, hw - hl)).
    inner_x, inner_y = max(hl - hw, 0.0), max(hw - hl, 0.0)
    t = (np.arange(PROBE_MEDIAL_AXIS_POINTS) + 0.5) / PROBE_MEDIAL_AXIS_POINTS
    axis = np.column_stack([inner_x + t * (hl - inner_x), inner_y + t * (hw - inner_y)])
    return np.vstack([axis * [sx, sy] for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))])


def _rounded(values: np.ndarray) -> list:
    return np.round(np.asarray(values, dtype=np.float64), STORED_DECIMALS).tolist()


def build_record(tensors: list[tuple[str, Any]], dual_fn: DualFunction, G: np.ndarray, g: np.ndarray,
                 error_statistics: dict[str, Any] | None) -> dict[str, Any]:
    """The integrity record of a net (see the module docstring); raises IntegrityError when the
    net cannot carry one (non-finite weights or outputs)."""
    from models.distance_net import rectangle_half_extents  # distance_net imports this module

    bad = nonfinite_weights(tensors)
    if bad:
        raise IntegrityError("the net has non-finite weights: " + "; ".join(bad))
    points = probe_points(*rectangle_half_extents(G, g))
    mu, _, distance = dual_fn(points)
    if not (np.isfinite(mu).all() and np.isfinite(distance).all()):
        raise IntegrityError("the net gives non-finite outputs on the probe set")
    _, exact = exact_dual(points, G, g)
    error = np.abs(distance - exact)
    outside = exact > 0.0
    stats = error_statistics or {}
    bound = {
        "outside_m": float(max(stats.get("max_abs_error_m", 0.0), error[outside].max()) + ERROR_BOUND_MARGIN_M),
        "inside_m": float(max(stats.get("inside_max_abs_error_m", 0.0), error[~outside].max()) + ERROR_BOUND_MARGIN_M),
        "margin_m": ERROR_BOUND_MARGIN_M,
        "rule": "per region: max(held-out max abs error, probe max abs error at save) + margin_m",
    }
    return {
        "weights_sha256": weights_checksum(tensors),
        "weights_checksum_rule": CHECKSUM_RULE,
        "n_weight_tensors": len(tensors),
        "error_bound": bound,
        "probe": {
            "rule": PROBE_RULE,
            "n_points": int(points.shape[0]),
            "output_tolerance": PROBE_OUTPUT_TOLERANCE,
            "mu": _rounded(mu),
            "distance_m": _rounded(distance),
            "exact_distance_m": _rounded(exact),
        },
    }


def _stored_array(probe: dict[str, Any], key: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(probe[key], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise IntegrityError(f"probe record lacks a numeric '{key}'") from exc
    if array.shape != shape or not np.isfinite(array).all():
        raise IntegrityError(f"probe record '{key}' has shape {array.shape} (expected {shape}) or non-finite values")
    return array


def _first_violation(excess: np.ndarray, points: np.ndarray) -> str:
    worst = int(np.argmax(excess))
    return f"at probe point {worst} {np.round(points[worst], 6).tolist()}"


def _record_mapping(record: Any) -> dict[str, Any]:
    if not isinstance(record, dict):
        raise IntegrityError("metadata 'integrity' is not a mapping")
    return record


def verify_weights(record: Any, tensors: list[tuple[str, Any]]) -> None:
    """The weights hash to the recorded checksum and are finite; else IntegrityError."""
    record = _record_mapping(record)
    checksum = weights_checksum(tensors)
    if record.get("weights_sha256") != checksum:
        raise IntegrityError(
            f"weight checksum mismatch: the weights hash to sha256 {checksum[:16]}..., the metadata "
            f"records {str(record.get('weights_sha256'))[:16]}... (weights changed after export)"
        )
    bad = nonfinite_weights(tensors)
    if bad:  # only reachable when the record was made for non-finite weights by hand
        raise IntegrityError("non-finite weights: " + "; ".join(bad))


def verify_probes(record: Any, dual_fn: DualFunction, G: np.ndarray, g: np.ndarray) -> None:
    """The net on the probe set reproduces the stored outputs and stays within the stored error
    bound of the exact distance; else IntegrityError naming the check and the probe point."""
    from models.distance_net import rectangle_half_extents  # distance_net imports this module

    probe = _record_mapping(record).get("probe")
    if not isinstance(probe, dict) or probe.get("rule") != PROBE_RULE:
        rule = probe.get("rule") if isinstance(probe, dict) else None
        raise IntegrityError(f"probe record rule {rule!r} is not '{PROBE_RULE}'")
    points = probe_points(*rectangle_half_extents(G, g))
    n = points.shape[0]
    if n < MIN_PROBE_POINTS or probe.get("n_points") != n:
        raise IntegrityError(f"probe record has n_points {probe.get('n_points')!r}, the rule gives {n}")
    stored_mu = _stored_array(probe, "mu", (n, G.shape[0]))
    stored_distance = _stored_array(probe, "distance_m", (n,))
    stored_exact = _stored_array(probe, "exact_distance_m", (n,))
    try:
        mu, _, distance = dual_fn(points)
    except Exception as exc:  # a module that is not our net fails in torch with any error type
        first_line = (str(exc).strip() or type(exc).__name__).splitlines()[0]
        raise IntegrityError(f"the module fails on the probe points: {type(exc).__name__}: {first_line}") from exc
    if not (np.isfinite(mu).all() and np.isfinite(distance).all()):
        raise IntegrityError("the net gives non-finite outputs on the probe points")
    for name, now, stored in (("mu", mu, stored_mu), ("distance", distance, stored_distance)):
        diff = np.abs(now - stored).reshape(n, -1).max(axis=1)
        if diff.max() > PROBE_OUTPUT_TOLERANCE:
            raise IntegrityError(
                f"probe outputs differ from the stored ones: {name} by {diff.max():.3g} > {PROBE_OUTPUT_TOLERANCE:g} "
                f"{_first_violation(diff, points)} (the net computes something else than when it was saved)"
            )
    _, exact = exact_dual(points, G, g)
    diff = np.abs(exact - stored_exact)
    if diff.max() > EXACT_DISTANCE_TOLERANCE_M:
        raise IntegrityError(
            f"stored exact probe distances differ from the exact distance by {diff.max():.3g} m "
            f"{_first_violation(diff, points)}"
        )
    _check_error_bound(record.get("error_bound"), distance, exact, points)


def _check_error_bound(bound: Any, distance: np.ndarray, exact: np.ndarray, points: np.ndarray) -> None:
    try:
        limits = {"outside": float(bound["outside_m"]), "inside": float(bound["inside_m"])}
    except (KeyError, TypeError, ValueError) as exc:
        raise IntegrityError("metadata 'integrity.error_bound' lacks numeric 'outside_m' and 'inside_m'") from exc
    if not all(math.isfinite(v) and v > 0.0 for v in limits.values()):
        raise IntegrityError(f"error bound {limits} is not finite and positive")
    outside = exact > 0.0
    error = distance - exact
    over = np.where(outside, error, -np.inf)
    if over.max() > OVERESTIMATE_TOLERANCE_M:
        raise IntegrityError(
            f"the net overestimates the distance outside by {over.max():.3g} m {_first_violation(over, points)} "
            "(it must stay a lower bound)"
        )
    for region, mask in (("outside", outside), ("inside", ~outside)):
        excess = np.where(mask, np.abs(error) - limits[region], -np.inf)
        if excess.max() > 0.0:
            worst = int(np.argmax(excess))
            raise IntegrityError(
                f"the net's error {abs(error[worst]):.3g} m exceeds its stored {region} error bound "
                f"{limits[region]:.3g} m {_first_violation(excess, points)}"
            )


__all__ = ["IntegrityError", "weight_tensors", "weights_checksum", "nonfinite_weights", "probe_points",
           "build_record", "verify_weights", "verify_probes", "PROBE_RULE", "CHECKSUM_RULE"]
