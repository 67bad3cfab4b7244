import os

# Offscreen rendering: there is no display on the test machines (docs/environment.md).
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
