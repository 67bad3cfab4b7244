"""Set-of-Mark prompting: numbered marks drawn on the image, so a VLM can name regions by number.

IMPACT section IV-A (after Yang et al., "Set-of-Mark prompting", arXiv 2310.11441): the image
the VLM sees carries, for each candidate region, its outline, a light tint and its number
1..N; the VLM answers "mark 3 is a cardboard box, cost 2" and we map mark 3 back to the third
region's mask at full resolution. The VLM never draws or returns masks itself.

Marks are drawn *after* downscaling to `max_side_px` so the numbers keep a legible size in the
picture the model actually sees (drawing first and shrinking would blur them). The number sits
at the pixel of the region farthest from its edge (the maximum of the distance transform),
which lies inside the region even when the region is not convex (a centroid may not).

Known limits: label boxes of regions that touch may overlap (Set-of-Mark's overlap resolution
is not done); a region that vanishes at the scaled size is marked at its box centre.
"""
from __future__ import annotations

import base64
from typing import Literal, Sequence

import cv2
import numpy as np

from models.vlm.interface import CandidateRegion

#: Distinct, saturated RGB colours (Tableau 10); mark k uses PALETTE[(k - 1) % 10].
PALETTE = np.array(
    [
        (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
        (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
    ],
    dtype=np.uint8,
)
#: How strongly a region is tinted with its colour (0 = outline only).
FILL_ALPHA = 0.25


def scale_for(shape_hw: tuple[int, int], max_side_px: int | None) -> float:
    """The factor (<= 1) that brings the image's longest side to at most max_side_px."""
    if max_side_px is None:
        return 1.0
    if max_side_px < 1:
        raise ValueError(f"max_side_px must be >= 1, got {max_side_px}")
    return min(1.0, max_side_px / max(shape_hw))


def mark_anchor(mask: np.ndarray) -> tuple[int, int] | None:
    """(x, y) of the mask pixel farthest from the mask's edge, or None for an empty mask."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    if not m.any():
        return None
    # Pad so the image border counts as outside the region.
    dist = cv2.distanceTransform(np.pad(m, 1), cv2.DIST_L2, 3)[1:-1, 1:-1]
    y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(x), int(y)


def draw_marks(
    image_rgb: np.ndarray, regions: Sequence[CandidateRegion], max_side_px: int | None = None
) -> np.ndarray:
    """A copy of the (H, W, 3) uint8 RGB image, downscaled to max_side_px, with region i
    (0-based) outlined, tinted and numbered i + 1. The input is not modified."""
    img = np.asarray(image_rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"draw_marks: expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    s = scale_for((h, w), max_side_px)
    out_w, out_h = max(1, round(w * s)), max(1, round(h * s))
    out = cv2.resize(img, (out_w, out_h), interpolation=cv2.INTER_AREA) if s < 1.0 else img.copy()

    side = max(out_h, out_w)
    thickness = max(1, round(side / 320))
    font_scale = max(0.5, side / 700)  # about 20 px tall digits at 1024 px
    font = cv2.FONT_HERSHEY_SIMPLEX

    masks = []
    for r in regions:
        m = np.asarray(r.mask, dtype=bool)
        if m.shape != (h, w):
            raise ValueError(f"draw_marks: region mask shape {m.shape}, image is {(h, w)}")
        if s < 1.0:
            m = cv2.resize(m.astype(np.uint8), (out_w, out_h), interpolation=cv2.INTER_NEAREST).astype(bool)
        masks.append(m)

    # Tint all regions first, then outlines, then numbers, so no later tint covers a number.
    for k, m in enumerate(masks):
        colour = PALETTE[k % len(PALETTE)].astype(np.float32)
        out[m] = (out[m] * (1.0 - FILL_ALPHA) + colour * FILL_ALPHA).astype(np.uint8)
    for k, m in enumerate(masks):
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, tuple(int(c) for c in PALETTE[k % len(PALETTE)]), thickness)
    for k, (r, m) in enumerate(zip(regions, masks)):
        anchor = mark_anchor(m)
        if anchor is None:  # vanished at this scale: the box centre, scaled
            x0, y0, x1, y1 = r.box_xyxy
            anchor = (int((x0 + x1) / 2 * s), int((y0 + y1) / 2 * s))
        text = str(k + 1)
        (tw, th), base = cv2.getTextSize(text, font, font_scale, thickness)
        pad = max(2, thickness)
        # The label box, centred on the anchor and kept inside the picture.
        bx0 = int(np.clip(anchor[0] - tw // 2 - pad, 0, max(0, out_w - tw - 2 * pad)))
        by0 = int(np.clip(anchor[1] - th // 2 - pad, 0, max(0, out_h - th - base - 2 * pad)))
        bx1, by1 = bx0 + tw + 2 * pad, by0 + th + base + 2 * pad
        colour = tuple(int(c) for c in PALETTE[k % len(PALETTE)])
        cv2.rectangle(out, (bx0, by0), (bx1, by1), (255, 255, 255), cv2.FILLED)
        cv2.rectangle(out, (bx0, by0), (bx1, by1), colour, max(1, thickness // 2))
        cv2.putText(out, text, (bx0 + pad, by0 + pad + th), font, font_scale, (0, 0, 0), thickness, cv2.LINE_AA)
    return out


def encode_data_url(image_rgb: np.ndarray, fmt: Literal["jpeg", "png"] = "jpeg", jpeg_quality: int = 90) -> str:
    """The RGB image as a `data:image/...;base64,...` URL for a chat-completions image_url part."""
    img = np.asarray(image_rgb)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"encode_data_url: expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    if fmt not in ("jpeg", "png"):
        raise ValueError(f"encode_data_url: fmt must be 'jpeg' or 'png', got {fmt!r}")
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)  # OpenCV encodes BGR
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", bgr, params)
    if not ok:
        raise ValueError(f"encode_data_url: OpenCV could not encode a {img.shape} image as {fmt}")
    return f"data:image/{fmt};base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def decode_data_url(url: str) -> np.ndarray:
    """The RGB image inside a data URL made by encode_data_url (for tests and debugging)."""
    head, _, payload = url.partition(",")
    if not head.startswith("data:image/") or not head.endswith(";base64"):
        raise ValueError(f"decode_data_url: not a base64 image data URL: {head[:40]!r}")
    bgr = cv2.imdecode(np.frombuffer(base64.b64decode(payload), np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("decode_data_url: the payload is not an image OpenCV can read")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


__all__ = ["PALETTE", "decode_data_url", "draw_marks", "encode_data_url", "mark_anchor", "scale_for"]
