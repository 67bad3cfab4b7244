"""The tracker's settings (controller config `vpp.tracking`)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class TrackingConfig(BaseModel):
    """Settings of the movable-object tracker (controller config `vpp.tracking`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    #: A template older than this since a mask last confirmed the object is dropped.
    max_unconfirmed_s: float = Field(8.0, gt=0.0, le=120.0)
    #: Fewer mask-labelled points than this do not confirm (a sliver at the image border).
    min_confirm_points: int = Field(10, ge=3, le=100000)
    #: Template thinning (m), and its size cap (points; a 0.4 m box at 3 cm: ~600).
    template_voxel_m: float = Field(0.03, gt=0.0, le=1.0)
    max_template_points: int = Field(600, ge=10, le=100000)
    #: Fixed points within this of the template's box (odom frame) are candidates (m): the
    #: object's motion in one scan (0.1 s) at most.
    search_margin_m: float = Field(0.25, gt=0.0, le=2.0)
    max_correspondence_m: float = Field(0.10, gt=0.0, le=1.0)
    icp_iterations: int = Field(6, ge=1, le=50)
    #: The registration fits every k-th template point, at most this many (a pushed box seen from
    #: close fills its template: all of them cost too much a scan; docs/decisions/vpp-tracking.md).
    icp_max_points: int = Field(150, ge=10, le=100000)
    #: Fewer matched pairs than this: not registered (the object is not in the scan this time).
    min_pairs: int = Field(12, ge=3, le=100000)
    #: A registration that moves the object farther than this in one scan is refused (m).
    max_step_m: float = Field(0.2, gt=0.0, le=2.0)
    #: A registration must match at least this share of the template within
    #: max_correspondence_m (its far side is hidden: not all of it), at most this rms (m)
    #: (docs/decisions/vpp-tracking.md).
    min_inlier_fraction: float = Field(0.5, gt=0.0, le=1.0)
    max_rms_m: float = Field(0.06, gt=0.0, le=1.0)
    #: Fixed points within this of the registered template join the object (m).
    label_radius_m: float = Field(0.06, gt=0.0, le=0.5)
    #: A fixed point up to this far behind the template along its own lidar ray (the ray passes
    #: within label_radius_m of a template point on its last behind_m) is the object's too: the
    #: lidar does not see through a solid object, and range noise (2 cm sigma on a Mid-360; the
    #: template's points carry theirs) puts 1-3 points a scan of a box's face 6-8 cm deep, and one
    #: of them left P_fix in front of the bumper blocks a push (docs/decisions/vpp-tracking.md).
    #: 0: off.
    behind_m: float = Field(0.10, ge=0.0, le=0.5)
    #: The template may span at most this much more than the newest confirming view (m).
    max_growth_m: float = Field(0.3, ge=0.0, le=5.0)
    #: The fixed points a template takes (its faces the camera never saw: the side the robot
    #: pushes on) join it while it spans at most this much more than the largest confirming
    #: view (m): a box pressed against a wall takes at most this much of the wall.
    max_spread_m: float = Field(0.1, ge=0.0, le=2.0)
    #: A mask's view of an object known (registered or seen) within the last max_unknown_s (a few
    #: scans) whose centre lies farther from the template's than half their two footprints and
    #: max_step_m is not the object: refused, and its points fixed
    #: (ObjectTracker._implausible_views), once the template has min_confirmations views (one
    #: view may have been the mistake: the next views replace it). An object unknown for longer
    #: may have moved unseen: its view is taken. A template whose views are all refused is not
    #: confirmed, and is dropped after max_unconfirmed_s.
    max_unknown_s: float = Field(0.3, ge=0.0, le=60.0)
    min_confirmations: int = Field(3, ge=1, le=1000)

    @model_validator(mode="after")
    def _fit_can_pair(self) -> "TrackingConfig":
        if self.icp_max_points < self.min_pairs:
            raise ValueError(f"icp_max_points ({self.icp_max_points}) must be at least min_pairs ({self.min_pairs}): "
                             "no registration could succeed")
        return self


__all__ = ["TrackingConfig"]
