import os

# MuJoCo picks its GL backend when it is first imported; EGL renders headless on this machine
# (OSMesa is not installed). An explicit MUJOCO_GL from the caller wins.
os.environ.setdefault("MUJOCO_GL", "egl")

# torch loads torch._dynamo (and triton's native libraries) lazily, at the first optimizer it
# builds; doing that while an earlier test's gRPC threads are still alive can segfault (as in
# esa_client.sb3), so the test session loads it before any channel exists.
import torch._dynamo  # noqa: E402, F401  (imported for its side effect)
