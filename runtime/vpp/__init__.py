"""VPP: the VLM point partition (DCT step 5).

Sub-packages and modules: homography/ (Phase I: masks carried to the current camera pose),
mask_memory.py (what is remembered of the VLM's answers; Phase II), partition/ (Phase III: every
lidar point P_mov or P_fix), tracking/ (movable objects followed between masks), deformable.py
(regions of deformable objects), belief.py (what each object is believed to be), in_front.py
(what lies in front of the robot), voxel_hash.py (the voxel table the partition's label memory
and the tracker share), stage.py (the stage that runs them per tick), config.py (its settings),
cli.py (`dct vpp`).
"""
