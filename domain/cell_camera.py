"""RGB-D frames of a cell camera, drawn from the hall's model without the other cells' geoms when
none of them can show (render culling: docs/physics.md)."""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

# A geom in this group is not drawn (MjvOption shows groups 0-2 by default): where rendering
# leaves out the other cells, their geoms sit in it for the duration of the render.
HIDDEN_GROUP = 5
CAMERA_DOWN_COS = 0.99  # a cell camera counts as looking straight down within ~8 degrees


class CellView:
    """Which geoms of the hall's ``model`` a cell camera cannot show: the other cells' geoms,
    when every one of them and its shadow lies outside the camera's view, checked at every frame
    from the geoms' current positions and bounding spheres. A camera that does not look straight
    down, a light that is not directional and a reflective material make every frame draw the
    hall."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.groups = model.geom_group.copy()
        cell_of = np.full(model.ngeom, -1)
        for gid in range(model.ngeom):
            for name in (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, gid),
                         mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[gid]))):
                head = (name or "").split("_", 1)[0]
                if head[:1] == "c" and head[1:].isdigit():
                    cell_of[gid] = int(head[1:])
                    break
        self.cell_of = cell_of
        self.visible = self.groups < 3  # what the default scene option draws
        # How far sideways a shadow falls per metre of height: the steepest directional light's.
        shadowed = model.light_castshadow.astype(bool)
        directional = model.light_type == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
        self.usable = bool((directional | ~shadowed).all()) and not (model.mat_reflectance > 0).any()
        dirs = model.light_dir[shadowed & directional]
        self.shadow_slope = max((math.hypot(d[0], d[1]) / max(-d[2], 1e-6) for d in dirs), default=0.0)
        self._others: dict[int, np.ndarray] = {}

    def out_of_view(self, data: mujoco.MjData, cell: int, camera: str, aspect: float) -> np.ndarray | None:
        """Ids of the geoms that camera ``camera`` (full model name) of cell ``cell`` cannot show
        in the state ``data`` at image aspect ``aspect`` (width / height), or None when some other
        cell's geom may be in view (then the whole hall is drawn)."""
        if not self.usable:
            return None
        cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        look = -data.cam_xmat[cam].reshape(3, 3)[:, 2]
        if look[2] > -CAMERA_DOWN_COS:
            return None
        others = self._others.get(cell)
        if others is None:
            others = self._others[cell] = np.flatnonzero(
                (self.cell_of >= 0) & (self.cell_of != cell) & self.visible)
        pos = data.cam_xpos[cam]
        # The view reaches farthest where it meets the floor: around the point below the camera,
        # at most its corner half-angle plus its tilt from the vertical.
        corner = math.atan(math.tan(math.radians(self.model.cam_fovy[cam]) / 2) * math.hypot(1.0, aspect))
        tilt = math.acos(min(1.0, -float(look[2])))
        reach = pos[2] * math.tan(min(corner + tilt, math.radians(89.0)))
        p = data.geom_xpos[others]
        rb = self.model.geom_rbound[others]
        gap = np.hypot(p[:, 0] - pos[0], p[:, 1] - pos[1]) - rb \
            - np.maximum(p[:, 2] + rb, 0.0) * self.shadow_slope
        if (rb > 0).all() and (gap > reach).all():
            return others
        return None


class CellCamera:
    """Renders the cell cameras of the hall's ``model`` with one offscreen renderer, which
    belongs to the thread that first renders (``close`` there)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.view = CellView(model)
        self._renderer: Any = None

    def render(self, data: mujoco.MjData, cell: int, width: int, height: int, camera: str = "camera",
               depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (uint8 HxWx3) and, if ``depth``, depth (float32 metres along the optical axis) of
        the state ``data`` seen by camera ``camera`` of cell ``cell``, ``width`` x ``height`` px."""
        if self._renderer is None or self._renderer.width != width or self._renderer.height != height:
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = mujoco.Renderer(self.model, height, width)
        r = self._renderer
        name = f"c{cell}_{camera}"
        hidden = self.view.out_of_view(data, cell, name, width / height)
        if hidden is not None:
            self.model.geom_group[hidden] = HIDDEN_GROUP
        try:
            r.disable_depth_rendering()
            r.update_scene(data, camera=name)
            rgb = r.render().copy()
            dep = None
            if depth:
                r.enable_depth_rendering()
                r.update_scene(data, camera=name)
                dep = r.render().copy()
                r.disable_depth_rendering()
        finally:
            if hidden is not None:
                self.model.geom_group[hidden] = self.view.groups[hidden]
        return rgb, dep

    def close(self) -> None:
        """Release the renderer (call this in the thread that rendered: a renderer left to the
        garbage collector fails on another thread)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
