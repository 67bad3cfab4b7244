"""Candidate regions: where in the image a VLM should look (DCT section IV-B, IMPACT section IV-A).

The DCT pipeline lets an open-set grounding detector propose regions and a VLM filter and grade
them (Set-of-Mark: `set_of_mark.py`, `openai_compatible.py`). A `RegionProposer` is that first
step: image + task prompt (+ optional lidar depth) in, `CandidateRegion`s out. Two proposers:

* `grounding_http.GroundingHttpProposer`: an open-set detector (Grounding DINO, optionally with
  SAM masks) behind a small REST API; its wire format is documented in that module.
* `OpenCvProposer` (here): the classical fallback, so the pipeline runs end to end with no model
  weights and no server. It knows nothing of the prompt (it is ignored): it proposes compact,
  uniformly coloured blobs of plausible size, which is what most pushable clutter (boxes, bins,
  bags, chairs' seats) looks like to a colour segmenter. The VLM decides what they are.

OpenCV pipeline (deterministic: no global RNG, fixed k-means initialisation):
1. Downscale to `work_side_px` (speed; masks are scaled back with nearest-neighbour).
2. Median blur (removes fine floor/wall texture, keeps object edges), convert to Lab, weight L
   down (`lightness_weight`: a shadow changes L far more than a and b).
3. k-means (`n_colors` clusters, k-means++ seeded by `seed`, fit on a strided subsample).
4. Canny edges on the blurred grey image, dilated once, cut the colour classes apart: two
   objects of similar colour that touch are separated where an edge runs between them. With
   lidar depth, depth jumps (`depth_edges`: neighbouring points more than `depth_jump_frac`
   apart in depth) cut them too: a grey box in front of a grey wall has no colour edge but
   has an occluding contour.
5. Connected components of each colour class minus edges become watershed seeds (components
   smaller than `seed_min_area_frac` are left unlabelled); `cv2.watershed` grows the seeds back
   over the edge pixels and the tiny fragments, so a region reaches its object's true outline.
6. Regions smaller than `min_area_frac` are merged into the neighbour of the closest mean
   colour (`absorb_small_regions`: colour noise and texture leave fragments inside and along
   objects). Regions are kept when their area is between `min_area_frac` and `max_area_frac`
   of the image (the floor and a wall are usually larger than any object), their box sides are
   at least `min_side_px`, and their fill ratio (area / box area) is at least `min_fill`
   (sprawling, stringy regions are texture or background, not objects).
7. score = fill ratio (0..1); ranking by area * fill (large and compact first); at most
   `max_regions`.
8. With lidar depth, each region carries the median camera-frame depth of the lidar points that
   fall inside it (at least `min_depth_points`, else None).

Known limits: two touching objects of the same colour with no visible edge (and no lidar depth
jump) between them come out as one region; a small fragment is merged by colour, not depth, so
it may cross a depth edge; an object with strong internal texture (a printed box) may split into parts; a
region larger than `max_area_frac` (a sofa filling the view) is dropped. Depth edges are as
coarse as the lidar's spacing (they only cut seeds; the boundary follows the image), and a
floor seen at a grazing angle may jump between scan lines and be cut into strips (it is
background, usually dropped as too large or too stringy anyway).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import ndimage

from models.vlm.interface import CandidateRegion
from models.vlm.set_of_mark import scale_for


class RegionProposalError(ValueError):
    """A proposer could not propose at all (bad input, detector down or answering garbage).
    The message names what was wrong. "No regions found" is not an error: it is ()."""


# ------------------------------------------------------------------------------------- depth


@dataclass(frozen=True, eq=False)
class SparseDepth:
    """Lidar points projected into the image: pixel (u, v) (x right, y down, pixel centres at
    integers, as `CameraModel.project`) and their camera-frame depth z in metres."""

    uv: np.ndarray  # (N, 2) float
    depth_m: np.ndarray  # (N,) float

    def __post_init__(self) -> None:
        uv = np.asarray(self.uv, dtype=np.float64)
        d = np.asarray(self.depth_m, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise RegionProposalError(f"depth uv: expected (N, 2), got {uv.shape}")
        if d.shape != (uv.shape[0],):
            raise RegionProposalError(f"depth depth_m: expected ({uv.shape[0]},) to match uv, got {d.shape}")
        object.__setattr__(self, "uv", uv)
        object.__setattr__(self, "depth_m", d)

    @classmethod
    def from_lidar(cls, camera, points_lidar: np.ndarray, T_cam_lidar: np.ndarray, min_depth_m: float = 0.05) -> "SparseDepth":
        """The points of an (N, 3) lidar scan that project into `camera` (a
        calibration.camera_model.CameraModel) in front of it, with their depths."""
        uv, valid, z = camera.depths_and_project_lidar(np.asarray(points_lidar, dtype=np.float64), T_cam_lidar)
        keep = valid & np.isfinite(z) & (z > min_depth_m)
        return cls(uv=uv[keep], depth_m=z[keep])


DepthInput = SparseDepth | tuple[np.ndarray, np.ndarray] | None


def as_sparse_depth(depth: DepthInput) -> SparseDepth | None:
    """A SparseDepth from a SparseDepth, a (uv, depth_m) pair or None."""
    if depth is None or isinstance(depth, SparseDepth):
        return depth
    if isinstance(depth, tuple) and len(depth) == 2:
        return SparseDepth(uv=depth[0], depth_m=depth[1])
    raise RegionProposalError(f"depth: expected SparseDepth, (uv, depth_m) or None, got {type(depth).__name__}")


def depth_pixels(depth: SparseDepth | None, image_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, col, depth_m) of the finite, positive depth points whose nearest pixel is in the image."""
    if depth is None or len(depth.depth_m) == 0:
        e = np.zeros(0, dtype=np.intp)
        return e, e, np.zeros(0)
    h, w = image_hw
    uv, d = depth.uv, depth.depth_m
    ok = np.isfinite(uv).all(axis=1) & np.isfinite(d) & (d > 0)
    uv, d = uv[ok], d[ok]
    cols = np.floor(uv[:, 0] + 0.5).astype(np.intp)
    rows = np.floor(uv[:, 1] + 0.5).astype(np.intp)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    return rows[inside], cols[inside], d[inside]


def median_depths(masks: Sequence[np.ndarray], depth: SparseDepth | None, min_points: int = 3) -> list[float | None]:
    """Per (H, W) bool mask: the median depth of the points inside it, None below min_points."""
    if not masks:
        return []
    rows, cols, d = depth_pixels(depth, masks[0].shape)
    out: list[float | None] = []
    for m in masks:
        sel = m[rows, cols]
        out.append(float(np.median(d[sel])) if int(sel.sum()) >= max(1, min_points) else None)
    return out


# ------------------------------------------------------------------------------------ helpers


def check_image(image: np.ndarray, who: str) -> np.ndarray:
    """The image as an (H, W, 3) uint8 array, else RegionProposalError naming what is wrong."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or img.shape[0] < 2 or img.shape[1] < 2:
        raise RegionProposalError(f"{who}: image must be (H, W, 3) uint8 RGB, got {img.shape} {img.dtype}")
    return img


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) of a bool mask (x1, y1 exclusive), None for an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def regions_from_masks(
    masks: Sequence[np.ndarray],
    scores: Sequence[float],
    labels: Sequence[str | None],
    depth: SparseDepth | None,
    min_depth_points: int = 3,
) -> tuple[CandidateRegion, ...]:
    """CandidateRegions (box from each mask, median depth attached); empty masks are skipped."""
    depths = median_depths(list(masks), depth, min_depth_points)
    out = []
    for m, s, lab, z in zip(masks, scores, labels, depths):
        box = mask_box(m)
        if box is None:
            continue
        out.append(CandidateRegion(mask=m, box_xyxy=box, score=float(min(1.0, max(0.0, s))), label_hint=lab, depth_m=z))
    return tuple(out)


class RegionProposer(Protocol):
    """Proposes regions worth asking a VLM about. May take a while (a detector over HTTP); runs
    outside the tick, beside the VLM backend."""

    name: str

    def propose(self, image: np.ndarray, prompt: str, depth: DepthInput = None) -> tuple[CandidateRegion, ...]:
        """Regions of the (H, W, 3) uint8 RGB image, best first; masks are (H, W) bool at the
        image's resolution. `prompt` names what to look for (detector text prompt; a proposer
        may ignore it). Raises RegionProposalError when it cannot propose at all."""
        ...


# ----------------------------------------------------------------------------- OpenCV fallback


class OpenCvProposerConfig(BaseModel):
    """The classical proposer's knobs (module docstring, steps 1..8). Areas are fractions of the
    image so one config fits every resolution."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    work_side_px: int = Field(default=480, ge=64, le=4096, description="segment at this longest side")
    blur_px: int = Field(default=5, ge=1, le=31, description="median blur aperture (odd)")
    n_colors: int = Field(default=8, ge=2, le=32, description="k-means colour classes")
    lightness_weight: float = Field(default=0.5, ge=0.0, le=2.0, description="weight of L against a, b")
    kmeans_iters: int = Field(default=12, ge=1, le=100)
    kmeans_samples: int = Field(default=20000, ge=100, le=1_000_000, description="pixels the centres are fit on")
    seed: int = Field(default=0, ge=0)
    canny_low: float = Field(default=40.0, ge=0.0, le=1000.0)
    canny_high: float = Field(default=100.0, ge=0.0, le=1000.0)
    seed_min_area_frac: float = Field(default=2e-4, ge=0.0, le=0.1, description="smaller fragments are not watershed seeds")
    min_area_frac: float = Field(default=0.002, ge=0.0, le=1.0)
    max_area_frac: float = Field(default=0.25, gt=0.0, le=1.0)
    min_side_px: int = Field(default=4, ge=1, description="box side at work resolution")
    min_fill: float = Field(default=0.35, ge=0.0, le=1.0, description="area / box area")
    max_regions: int = Field(default=12, ge=1, le=256)
    min_depth_points: int = Field(default=3, ge=1)
    depth_jump_frac: float | None = Field(
        default=0.25, gt=0.0, le=10.0,
        description="neighbouring lidar depths differing by more than this fraction cut regions; None: off")
    depth_max_gap_px: float = Field(default=10.0, gt=0.0, description="no depth edge farther than this from a lidar point (work px)")

    @model_validator(mode="after")
    def _consistent(self) -> "OpenCvProposerConfig":
        if self.blur_px % 2 == 0:
            raise ValueError(f"blur_px must be odd, got {self.blur_px}")
        if self.min_area_frac >= self.max_area_frac:
            raise ValueError(f"min_area_frac ({self.min_area_frac}) must be below max_area_frac ({self.max_area_frac})")
        if self.canny_low > self.canny_high:
            raise ValueError(f"canny_low ({self.canny_low}) must not exceed canny_high ({self.canny_high})")
        return self


def kmeans_lab(features: np.ndarray, k: int, iters: int, n_samples: int, seed: int) -> np.ndarray:
    """(P,) int labels of (P, C) float32 features: Lloyd's k-means fit on a strided subsample with
    a seeded k-means++ start, then every pixel assigned to its nearest centre. Deterministic."""
    p = features.shape[0]
    stride = max(1, p // n_samples)
    sample = features[::stride]
    rng = np.random.default_rng(seed)
    centres = [sample[rng.integers(len(sample))]]
    d2 = ((sample - centres[0]) ** 2).sum(axis=1)
    for _ in range(1, k):
        total = float(d2.sum())
        if total <= 0.0:  # fewer distinct colours than k: duplicates are harmless
            centres.append(centres[-1])
            continue
        c = sample[rng.choice(len(sample), p=d2 / total)]
        centres.append(c)
        d2 = np.minimum(d2, ((sample - c) ** 2).sum(axis=1))
    C = np.stack(centres).astype(np.float32)
    for _ in range(iters):
        lab = _nearest(sample, C)
        sums = np.zeros_like(C, dtype=np.float64)
        np.add.at(sums, lab, sample)
        counts = np.bincount(lab, minlength=k)
        nz = counts > 0
        new = C.copy()
        new[nz] = (sums[nz] / counts[nz, None]).astype(np.float32)
        if np.allclose(new, C, atol=1e-3):
            C = new
            break
        C = new
    return _nearest(features, C)


def _nearest(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    # |x - c|^2 = |x|^2 - 2 x.c + |c|^2; |x|^2 is common to all c.
    d = (centres**2).sum(axis=1)[None, :] - 2.0 * (x @ centres.T)
    return np.argmin(d, axis=1).astype(np.intp)


def depth_edges(depth: SparseDepth | None, full_hw: tuple[int, int], work_hw: tuple[int, int],
                jump_frac: float, max_gap_px: float) -> np.ndarray:
    """(h, w) bool at work resolution: where the lidar depth jumps (an occluding contour).

    Each work pixel takes the depth of its nearest lidar point (the nearest surface where two
    points share a pixel); a pixel whose right or lower neighbour's depth differs by more than
    `jump_frac` of the nearer one lies on a jump. Jumps farther than `max_gap_px` from any point
    (the gaps between scan lines, regions the lidar does not see) are not trusted. The result is
    coarse (a Voronoi line between points); it only cuts seeds, and the watershed puts the final
    boundary where the image's gradient is."""
    h, w = work_hw
    rows, cols, d = depth_pixels(depth, full_hw)
    edges = np.zeros((h, w), dtype=bool)
    if d.size < 2:
        return edges
    H, W = full_hw
    r = np.minimum(((rows + 0.5) * (h / H)).astype(np.intp), h - 1)
    c = np.minimum(((cols + 0.5) * (w / W)).astype(np.intp), w - 1)
    grid = np.full((h, w), np.inf)
    np.minimum.at(grid, (r, c), d)
    dist, (ir, ic) = ndimage.distance_transform_edt(~np.isfinite(grid), return_indices=True)
    dense = grid[ir, ic]
    jx = np.abs(dense[:, 1:] - dense[:, :-1]) > jump_frac * np.minimum(dense[:, 1:], dense[:, :-1])
    jy = np.abs(dense[1:, :] - dense[:-1, :]) > jump_frac * np.minimum(dense[1:, :], dense[:-1, :])
    edges[:, :-1] |= jx
    edges[:, 1:] |= jx
    edges[:-1, :] |= jy
    edges[1:, :] |= jy
    return edges & (dist <= max_gap_px)


def absorb_small_regions(labels: np.ndarray, min_area: int, features: np.ndarray | None = None,
                         max_passes: int = 4) -> np.ndarray:
    """Labels with every region smaller than min_area merged into a neighbour: a large neighbour
    before a small one, then the neighbour of the closest mean feature (colour; with no features
    given, the one it shares the longest border with), ties by the longer border, then the lower
    id. Why: colour noise and texture split an object into one large piece and fragments; the
    fragments would be dropped as too small, leaving holes and a ragged outline. Merges only go
    to a larger region (ties: the lower id), so there are no cycles. Label 0 (no region) is
    neither merged nor merged into."""
    labels = np.asarray(labels)
    for _ in range(max_passes):
        n = int(labels.max()) + 1
        flat = labels.ravel()
        area = np.bincount(flat, minlength=n)
        small = (area > 0) & (area < min_area)
        small[0] = False
        if not small.any():
            break
        a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
        b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
        differ = a != b
        src = np.concatenate([a[differ], b[differ]]).astype(np.int64)
        dst = np.concatenate([b[differ], a[differ]]).astype(np.int64)
        ok = small[src] & (dst != 0) & ((area[dst] > area[src]) | ((area[dst] == area[src]) & (dst < src)))
        src, dst = src[ok], dst[ok]
        if src.size == 0:
            break
        pairs, border = np.unique(src * n + dst, return_counts=True)
        s_, d_ = pairs // n, pairs % n
        if features is not None:
            f = features.reshape(flat.size, -1).astype(np.float64)
            mean = np.stack([np.bincount(flat, weights=f[:, k], minlength=n) for k in range(f.shape[1])], axis=1)
            mean /= np.maximum(area, 1)[:, None]
            dist = np.linalg.norm(mean[s_] - mean[d_], axis=1)
        else:
            dist = np.zeros(s_.size)
        order = np.lexsort((d_, -border, dist, small[d_], s_))  # last key first: by source, large first, ...
        s_o, d_o = s_[order], d_[order]
        first = np.ones(s_o.size, dtype=bool)
        first[1:] = s_o[1:] != s_o[:-1]
        lut = np.arange(n, dtype=labels.dtype)
        lut[s_o[first]] = d_o[first]
        for _ in range(64):  # follow chains a -> b -> c (acyclic: area grows along them)
            nxt = lut[lut]
            if np.array_equal(nxt, lut):
                break
            lut = nxt
        labels = lut[labels]
    return labels


def _colour_seeds(colour: np.ndarray, edges: np.ndarray, n_colors: int, seed_min: int) -> tuple[np.ndarray, int]:
    """Seeds: connected pieces of one colour class that no edge crosses, of at least `seed_min`
    pixels, numbered from 1. Returns the marker image and the next free id."""
    h, w = colour.shape
    markers = np.zeros((h, w), np.int32)
    next_id = 1
    for c in range(n_colors):
        part = ((colour == c) & ~edges).astype(np.uint8)
        if not part.any():
            continue
        n, cc, stats, _ = cv2.connectedComponentsWithStats(part, connectivity=4)
        keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= seed_min) + 1
        if keep.size == 0:
            continue
        lut = np.zeros(n, np.int32)
        lut[keep] = np.arange(next_id, next_id + keep.size, dtype=np.int32)
        next_id += keep.size
        sel = lut[cc]
        markers = np.where(sel > 0, sel, markers)
    return markers, next_id


def _grow_seeds(blur: np.ndarray, markers: np.ndarray) -> None:
    """Grow the seeds over edges and fragments (in place), then give the watershed's -1 lines (and
    the image border, which cv2.watershed marks -1) to a neighbouring region."""
    cv2.watershed(cv2.cvtColor(blur, cv2.COLOR_RGB2BGR), markers)
    line = markers < 0
    if line.any():
        grown = cv2.dilate(np.where(line, 0, markers).astype(np.float32), np.ones((3, 3), np.uint8))
        markers[line] = grown[line].astype(np.int32)


def _rank_regions(markers: np.ndarray, n_ids: int, cfg: OpenCvProposerConfig) -> tuple[list[int], list[float]]:
    """The region ids that pass the size and fill tests, best first (area x fill), with their
    scores (the fill of their bounding box)."""
    h, w = markers.shape
    area = np.bincount(markers.ravel(), minlength=n_ids).astype(np.float64)
    ids, scores, keys = [], [], []
    for i, sl in enumerate(ndimage.find_objects(markers, max_label=n_ids - 1), start=1):
        if sl is None:
            continue
        bh, bw = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        a = area[i]
        fill = a / float(bh * bw)
        frac = a / float(h * w)
        if not (cfg.min_area_frac <= frac <= cfg.max_area_frac) or min(bh, bw) < cfg.min_side_px or fill < cfg.min_fill:
            continue
        ids.append(i)
        scores.append(float(fill))
        keys.append(a * fill)
    order = sorted(range(len(ids)), key=lambda j: (-keys[j], ids[j]))[: cfg.max_regions]
    return [ids[j] for j in order], [scores[j] for j in order]


class OpenCvProposer:
    """Colour/edge segmentation proposer (module docstring). Thread-safe, stateless."""

    name = "opencv"

    def __init__(self, config: OpenCvProposerConfig | None = None):
        self.config = config or OpenCvProposerConfig()

    def segment(self, image: np.ndarray, depth: SparseDepth | None = None) -> tuple[np.ndarray, list[int], list[float]]:
        """(labels at work resolution (h, w) int32, kept ids best first, their scores). Steps 1..7;
        with depth (and depth_jump_frac set), lidar depth jumps cut seeds as image edges do."""
        cfg = self.config
        img = check_image(image, "opencv proposer")
        H, W = img.shape[:2]
        s = scale_for((H, W), cfg.work_side_px)
        w, h = max(2, round(W * s)), max(2, round(H * s))
        small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if s < 1.0 else np.ascontiguousarray(img)
        blur = cv2.medianBlur(small, cfg.blur_px) if cfg.blur_px > 1 else small

        lab = cv2.cvtColor(blur, cv2.COLOR_RGB2LAB).astype(np.float32)
        lab[..., 0] *= cfg.lightness_weight
        colour = kmeans_lab(lab.reshape(-1, 3), cfg.n_colors, cfg.kmeans_iters, cfg.kmeans_samples, cfg.seed).reshape(h, w)

        grey = cv2.cvtColor(blur, cv2.COLOR_RGB2GRAY)
        edges = cv2.dilate(cv2.Canny(grey, cfg.canny_low, cfg.canny_high), np.ones((3, 3), np.uint8)) > 0
        if depth is not None and cfg.depth_jump_frac is not None:
            edges |= depth_edges(depth, (H, W), (h, w), cfg.depth_jump_frac, cfg.depth_max_gap_px)

        markers, next_id = _colour_seeds(colour, edges, cfg.n_colors, max(1, int(cfg.seed_min_area_frac * h * w)))
        if next_id == 1:
            return markers, [], []
        _grow_seeds(blur, markers)
        markers = absorb_small_regions(markers, max(1, int(cfg.min_area_frac * h * w)), lab)
        ids, scores = _rank_regions(markers, next_id, cfg)
        return markers, ids, scores

    def propose(self, image: np.ndarray, prompt: str = "", depth: DepthInput = None) -> tuple[CandidateRegion, ...]:
        """Regions best first (module docstring). `prompt` is ignored: this proposer is not open-set."""
        img = check_image(image, "opencv proposer")
        sd = as_sparse_depth(depth)
        markers, ids, scores = self.segment(img, sd)
        if not ids:
            return ()
        H, W = img.shape[:2]
        if markers.shape != (H, W):
            markers = cv2.resize(markers.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST).astype(np.int32)
        masks = [markers == i for i in ids]
        return regions_from_masks(masks, scores, [None] * len(masks), sd, self.config.min_depth_points)


__all__ = [
    "DepthInput",
    "OpenCvProposer",
    "OpenCvProposerConfig",
    "RegionProposalError",
    "RegionProposer",
    "SparseDepth",
    "as_sparse_depth",
    "check_image",
    "absorb_small_regions",
    "depth_edges",
    "depth_pixels",
    "kmeans_lab",
    "mask_box",
    "median_depths",
    "regions_from_masks",
]
