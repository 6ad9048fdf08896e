"""The physics service: the MuJoCo factory hall (scene, arm model, world) and its federate."""

import os

# MuJoCo picks its OpenGL backend when it is first imported; every module of this package may
# be the first to import it, and the package runs before any of them: headless EGL by default.
os.environ.setdefault("MUJOCO_GL", "egl")
