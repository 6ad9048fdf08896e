"""The domain: code that more than one federate (or a training or measurement script) runs, with
no bus and no process of its own (the cell, the arm, perception, the co-design policies and the
compute workloads). Federates import the domain and the fabric, never each other."""

import os

# MuJoCo picks its OpenGL backend when it is first imported; any module of this package may be
# the first to import it, and the package runs before any of them: headless EGL by default.
os.environ.setdefault("MUJOCO_GL", "egl")
