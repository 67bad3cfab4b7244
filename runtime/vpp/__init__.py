"""VPP (DCT paper IV-B): masks from a VLM, mask memory and warp, and the movable/fixed point partition."""
