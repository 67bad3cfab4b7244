"""Movable objects followed between masks: a rigid point template per object, registered to each scan.

Why: the mask memory's warp assumes that an object stands still (Phase I). The object the robot
pushes does not: it stays in front of the robot while the warp carries its mask towards the
image border and grows it, and the stage stops trusting the mask (VppConfig.max_mask_growth).
Between two masks that see it, the object's lidar points must still be P_mov, or the planner
sees a fixed wall in front of the bumper and stops. The camera also sees less than the lidar
(its field of view is narrower): the parts of a tracked object beside the robot are known only
from here.

How, per object, with the points of one scan in the odom frame:
- Confirmation: the scan points a mask labelled movable for the object, in view, become its
  template (plus the previous template's points the new view does not cover, as long as the
  union spans no more than `max_growth_m` beyond the new view: a far view shows one face, a
  near one the rest). A template holds only points a mask confirmed, moved rigidly since: never
  points it picked up by being near them, so it cannot creep into a wall the object touches.
- Tracking: every scan, each template (of an object a mask confirmed less than
  `max_unconfirmed_s` ago) is registered to the scan's fixed points near it (and its own) by a
  few iterations of planar point-to-point ICP (yaw and x, y: a pushed object slides on the
  floor), with correspondences within `max_correspondence_m`; a step larger than `max_step_m`
  is refused (the template stays where it was). Then a mask's view, if any, is merged (a view
  that disagrees with the template: the bigger of the two wins, so that a sliver at the image
  border does not replace the object), and every fixed point within `label_radius_m` of the
  template takes the object's id and cost: the parts of the object the camera does not see.
- Spread: the fixed points a template takes join it (the faces of the object the camera never
  saw, which the robot may be pushing on) while the template spans at most `max_spread_m` more
  than the largest view a mask confirmed: a box pressed against a wall takes at most that much
  of the wall.
- Plausibility: a mask's view of an object the tracker knows where it is (registered this scan,
  or registered or seen within `max_unknown_s`) whose centre lies farther from the template's
  than half their footprints and `max_step_m` is not the object: refused, and its points are
  fixed (_implausible_views: a view that replaced the template there took a wall for a box);
  the caller fixes them in its label memory too (`refused_points`). Only a template of at
  least `min_confirmations` views is trusted so; one whose views are all refused expires.
- Identity: the mask memory gives an object a new id when its warped mask stops matching the
  fresh one (it moved); a new id whose view lies mostly on a tracked template takes that
  template over (and its confirmation time), so one box is one tracked object.
Points a tracked object would take are only ever FIXED ones (not ground, not another object's).

Templates, not label spreading from the previous scan's movable points: a spread hops into
whatever the object touches (docs/decisions/vpp-tracking.md).

Cost: a template is voxel-thinned to `template_voxel_m` (a 0.4 m box: ~200 points); per object
and scan one compiled pass each for the registration (a grid of the candidate points, at most
`icp_iterations` nearest-neighbour rounds), the labelling and the merge of a mask's view: about
0.1 ms an object (`dct bench vpp`).

Modules: config.py (TrackingConfig), tracker.py (ObjectTracker, TrackedObject), and its
compiled kernels: scan_select.py (which scan points to look at), registration.py (ICP),
templates.py (merging views, spreading), labelling.py (taking points), geometry.py (boxes,
sizes, thinning).
"""
