import os

# MuJoCo picks its GL backend when it is first imported; EGL renders headless on this machine
# (OSMesa is not installed). An explicit MUJOCO_GL from the caller wins.
os.environ.setdefault("MUJOCO_GL", "egl")
