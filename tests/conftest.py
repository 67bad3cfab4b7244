import os
import zlib

# Offscreen rendering: a robot computer or a CI machine has no display (docs/environment.md).
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def pytest_collection_modifyitems(config, items):
    """DCT_SLOW_SHARD=i/n keeps the slow tests whose id hashes to shard i of n (the others are
    deselected): `.ci/run` runs one shard of the slow tests per commit, a different one each
    time, so that every slow test runs every n commits and none can rot."""
    shard = os.environ.get("DCT_SLOW_SHARD")
    if not shard:
        return
    try:
        i, n = (int(v) for v in shard.split("/"))
    except ValueError:
        raise SystemExit(f"DCT_SLOW_SHARD={shard!r}: expected i/n (two whole numbers)") from None
    if not 0 <= i < n:
        raise SystemExit(f"DCT_SLOW_SHARD={shard!r}: the shard i must be in 0..n-1")
    keep, drop = [], []
    for item in items:
        if item.get_closest_marker("slow") is not None and zlib.crc32(item.nodeid.encode()) % n != i:
            drop.append(item)
        else:
            keep.append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
