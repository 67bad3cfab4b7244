"""No compiled kernel is compiled or loaded inside a tick: every signature a tick uses is met in
the parts' warm-ups at start-up (a compile in the tick costs hundreds of milliseconds: a missed
deadline; a load from numba's cache, milliseconds)."""
import json
import os
import subprocess
import sys
from pathlib import Path

PROBE = Path(__file__).with_name("tick_compile_probe.py")


def test_a_case1_episode_adds_no_kernel_signature_inside_a_tick():
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run([sys.executable, str(PROBE), "case1"], capture_output=True, text=True, timeout=600,
                          env=env, cwd=Path(__file__).parents[2])
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["ticks"] > 50 and out["success"]
    assert out["signatures_added"] > 0  # the probe sees the warm-ups' loads: it would see a tick's
    assert out["in_tick"] == []
