import os

# Offscreen rendering: there is no display on these machines (ENVIRONMENT.md).
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
