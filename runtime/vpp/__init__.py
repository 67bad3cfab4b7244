"""VPP: the VLM point partition (DCT step 5): mask memory, homography warp, point partition."""
