"""VPP Phase III (DCT paper IV-B-c): label every lidar point movable (P_mov) or fixed (P_fix).

Per scan, with the reconciled masks of this instant (each an (H, W) bool bitmap with an object id
and an IMPACT-style contact cost 0..10):

1. Ground removal: points with height (base frame) below `ground_max_z_m`, and/or the points a
   caller marks `ignore`, get the label IGNORED and take no further part (the planner never sees
   them; the paper removes the ground before partitioning).
2. Projection (eq. 7): p_cam = T_cam_lidar p, pixel = K distort(p_cam / z) with the CameraModel
   (distortion included). Points behind the camera, outside the distortion model's domain or
   outside the image are "unseen" (`in_view` False).
3. Gating (eqs. 8-9): a seen point whose nearest pixel centre is set in some mask is movable, with
   that mask's object id and cost; where masks overlap the highest cost wins (the conservative
   reading: touch it as gently as the strictest object there asks). Every other point is fixed
   (object id -1, cost NaN). Known limit: a point is clustered only with the mask that won it,
   so where a sloppy high-cost mask overlaps another object, that object's points there can be
   suppressed as the high-cost object's outliers and end fixed (safe, but lost recall).
4. Cluster refinement, as the paper ("3D Euclidean clustering (e.g. DBSCAN with radius
   eps_cluster and minimum size N_min)"), per object so that two touching objects stay apart:
   - Clusters are the connected components of the graph "same object and 3-D distance <=
     eps_cluster" (Euclidean cluster extraction as PCL's; DBSCAN with min_samples = 1 --
     a DBSCAN core-point rule would only shave cluster borders, which completion adds back).
   - Outlier suppression: movable points in a component smaller than N_min become fixed (the
     paper's rule). Beyond the paper, with `max_depth_gap_m` set, a component is kept only if
     its mean camera depth is within that gap of the object's dominant (largest) component: a
     mask's edge overlaps the background, and the background seen through it (a wall, the road
     behind a car) can be a big connected strip of >= N_min points that the size rule alone
     would keep. A mask is one object, so the dominant component is the object; other
     components at its depth are the same object split by the lidar's ring spacing.
   - Completion: a fixed point (non-ground, seen) becomes movable for object k when it lies
     within eps_cluster of a kept point of k (one hop, against the clusters after suppression,
     as the paper's dist(p, C_k) <= eps) AND its pixel lies in the mask of k dilated by a
     square of half-size `completion_dilate_px`. The image condition is the brief's; it stops
     completion from eating into a wall or a neighbour the object touches in 3-D but that the
     VLM did not paint (a box against a wall: only the wall points next to the box's
     silhouette can join). Points that suppression just removed are not re-added.
5. Label memory (odom frame): seen, non-ground points write their final label into a 3-D voxel
   hash (voxel -> label, object id, cost, stamp); unseen points take their voxel's remembered
   label if it is younger than `memory_max_age_s`, else fixed (the safe default). Within one
   scan a voxel with any fixed point is fixed (a voxel straddling a box and the wall behind it
   must not make the wall touchable); among movable points the highest cost wins.

Modules: labels.py (the labels, PointPartition), config.py (PartitionConfig), inputs.py (the
checks), projection.py (steps 1-2: one compiled pass), gating.py (step 3: the mask lookup),
clustering.py (step 4: the refinement), label_memory.py (step 5), partitioner.py
(PointPartitioner: the steps in order, per scan). Everything per point runs in numba kernels or
numpy; there is no Python loop over points or masks in the tick.

Budget: the whole VPP stage per scan within 3 ms p99 at 20k points and 8 masks of 640x480 on one
core; `dct bench vpp` (hil_sim/bench/vpp.py) measures it, its `partition` column this step
inside the stage (docs/decisions/vpp-compiled-kernels.md for what the kernels' shape buys).
"""
