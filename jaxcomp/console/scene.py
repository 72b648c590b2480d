"""The console's 3D scene: the robot drawn from its MuJoCo model, the target, the end
effector's trail and the external force, on a viser server (in the page's process).

Each body of the model is a scene frame, posed every frame from the arm's joint angles and the
base's odometry by MuJoCo's forward kinematics (``mj_kinematics`` on the page's own
``MjData``); its geoms hang under it as meshes: boxes, spheres, capsules, cylinders and
ellipsoids from their sizes, and the model's own triangle meshes where it has them. The floor
plane is a grid. World frame, z up, m.
"""

from __future__ import annotations

from collections import deque

import mujoco
import numpy as np

from jaxcomp.robot import Robot

#: Newtons per metre of the force arrow (10 N: 0.2 m).
ARROW_SCALE = 0.02
#: Points kept in the end effector's trail (10 s at 30 Hz).
TRAIL = 300
_RINGS, _SEGMENTS = 8, 16  # tessellation of round geoms


def _sphere(radius: np.ndarray, rings: int = _RINGS, segments: int = _SEGMENTS):
    """(vertices, faces) of an ellipsoid with semi-axes ``radius`` (3,) m."""
    theta = np.linspace(0.0, np.pi, rings + 1)[:, None]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    x, y = np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi)
    v = np.stack([x, y, np.broadcast_to(np.cos(theta), x.shape)], -1)
    return _grid_faces(v.reshape(-1, 3) * radius, rings + 1, segments)


def _grid_faces(vertices: np.ndarray, rows: int, cols: int):
    """Faces joining a closed-in-``cols`` grid of ``rows`` x ``cols`` vertices."""
    faces = []
    for i in range(rows - 1):
        for j in range(cols):
            a, b = i * cols + j, i * cols + (j + 1) % cols
            c, d = a + cols, b + cols
            faces += [(a, c, b), (b, c, d)]
    return vertices, np.array(faces, dtype=np.uint32)


def _capsule(radius: float, half: float):
    """A capsule along z: two hemispheres of ``radius`` m ``2 half`` m apart."""
    v, f = _sphere(np.full(3, radius), rings=2 * (_RINGS // 2) + 1)
    v = v.copy()
    v[:, 2] += np.where(v[:, 2] >= 0, half, -half)
    return v, f


def _cylinder(radius: float, half: float):
    """A closed cylinder along z, ``radius`` m, from -half to half m."""
    phi = np.linspace(0.0, 2 * np.pi, _SEGMENTS, endpoint=False)
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], -1)
    side = np.concatenate([np.c_[ring, np.full(_SEGMENTS, z)] for z in (-half, half)])
    v, f = _grid_faces(side, 2, _SEGMENTS)
    v = np.vstack([v, [[0.0, 0.0, -half], [0.0, 0.0, half]]])
    lo, hi = len(v) - 2, len(v) - 1
    caps = []
    for j in range(_SEGMENTS):
        k = (j + 1) % _SEGMENTS
        caps += [(lo, k, j), (hi, _SEGMENTS + j, _SEGMENTS + k)]
    return v, np.vstack([f, np.array(caps, dtype=np.uint32)])


def _box(half: np.ndarray):
    """A box of half sizes ``half`` (3,) m."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    faces = [
        (0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
        (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3),
    ]  # fmt: skip
    return corners * half, np.array(faces, dtype=np.uint32)


def geom_mesh(model: mujoco.MjModel, g: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (V, 3) m, faces (F, 3)) of geom ``g`` in its own frame, or None for what is
    not drawn as a mesh (planes, height fields, lines).

    Args:
        model: the MuJoCo model.
        g: the geom's index.

    Returns:
        (vertices (V, 3) float m, faces (F, 3) uint32 vertex indices), or None.
    """
    t, size = int(model.geom_type[g]), model.geom_size[g]
    kind = mujoco.mjtGeom
    if t == kind.mjGEOM_SPHERE:
        return _sphere(np.full(3, size[0]))
    if t == kind.mjGEOM_ELLIPSOID:
        return _sphere(size[:3])
    if t == kind.mjGEOM_CAPSULE:
        return _capsule(size[0], size[1])
    if t == kind.mjGEOM_CYLINDER:
        return _cylinder(size[0], size[1])
    if t == kind.mjGEOM_BOX:
        return _box(size[:3])
    if t == kind.mjGEOM_MESH:
        m = int(model.geom_dataid[g])
        v0, nv = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        f0, nf = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
        return model.mesh_vert[v0 : v0 + nv].copy(), model.mesh_face[f0 : f0 + nf].astype(np.uint32)
    return None


def geom_color(model: mujoco.MjModel, g: int) -> tuple[tuple[int, int, int], float]:
    """(RGB 0-255, opacity) of geom ``g``: its material's colour, else its own.

    Args:
        model: the MuJoCo model.
        g: the geom's index.

    Returns:
        ((r, g, b) ints 0-255, opacity 0-1).
    """
    mat = int(model.geom_matid[g])
    rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
    rgb = tuple(int(round(255 * float(c))) for c in rgba[:3])
    return rgb, float(rgba[3])


class RobotScene:
    """The robot and its markers on ``server`` (a ``viser.ViserServer``).

    ``robot``: the whole model (a mobile manipulator with its base joints); ``arm_joints`` and
    ``base_joints``: the names of the joints a frame's q and base pose (x, y, yaw) set.
    """

    def __init__(self, server, robot: Robot, arm_joints, base_joints=()):
        self.server = server
        self.model = m = robot.model
        self.data = mujoco.MjData(m)
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name) for name in arm_joints]
        self._qadr = m.jnt_qposadr[jid]
        bid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name) for name in base_joints]
        self._badr = m.jnt_qposadr[bid] if len(bid) == 3 else None
        self.data.qpos[:] = m.qpos0
        server.scene.set_up_direction("+z")
        # no image-based lighting: its set-up freezes a software-rendered page (a browser
        # without a GPU, a phone) for seconds; the default lights, without shadows, and an
        # ambient one instead
        server.scene.configure_environment_map(None)
        server.scene.configure_default_lights(True, cast_shadow=False)
        server.scene.add_light_ambient("/ambient", intensity=0.6)
        server.scene.add_grid("/floor", width=6.0, height=6.0, cell_size=0.25, section_size=1.0)
        self.bodies = {}
        self.geoms = 0
        for g in range(m.ngeom):
            if int(m.geom_group[g]) > 2:
                continue  # collision-only groups
            mesh = geom_mesh(m, g)
            if mesh is None:
                continue
            b = int(m.geom_bodyid[g])
            if b not in self.bodies:
                self.bodies[b] = server.scene.add_frame(f"/robot/body{b}", show_axes=False)
            rgb, alpha = geom_color(m, g)
            server.scene.add_mesh_simple(
                f"/robot/body{b}/geom{g}",
                mesh[0].astype(np.float32),
                mesh[1],
                color=rgb,
                opacity=None if alpha >= 1.0 else alpha,
                position=m.geom_pos[g].copy(),
                wxyz=m.geom_quat[g].copy(),
                cast_shadow=False,
                receive_shadow=False,
            )
            self.geoms += 1
        self.target = server.scene.add_icosphere(
            "/target", radius=0.015, color=(220, 30, 30), visible=False
        )
        zero = np.zeros((1, 2, 3), np.float32)
        self.arrow = server.scene.add_arrows(
            "/force", zero, colors=(250, 120, 0), shaft_radius=0.006, head_radius=0.014,
            head_length=0.03, visible=False,
        )  # fmt: skip
        self.band = server.scene.add_box(
            "/force_band", dimensions=(1.0, 1.0, 1.0), color=(250, 120, 0), wireframe=True,
            visible=False,
        )  # fmt: skip
        self._trail = server.scene.add_line_segments(
            "/trail", zero, colors=(40, 120, 230), thickness=2.0, thickness_units="screen",
            visible=False,
        )  # fmt: skip
        self.trail: deque = deque(maxlen=TRAIL)
        self._frames = 0

    def pose(self, q: np.ndarray, base: np.ndarray | None) -> None:
        """Pose every body for arm joint angles ``q`` (rad) and base pose ``base``.

        Args:
            q: (n,) arm joint angles, rad, in the order of ``arm_joints``.
            base: (3,) the base's (x m, y m, yaw rad), world frame; None, not finite, or a
                model without the three base joints: the base stays where it was.
        """
        m, d = self.model, self.data
        d.qpos[self._qadr] = q
        if self._badr is not None and base is not None and np.all(np.isfinite(base)):
            d.qpos[self._badr] = base
        mujoco.mj_kinematics(m, d)
        for b, frame in self.bodies.items():
            frame.position = d.xpos[b].copy()
            frame.wxyz = d.xquat[b].copy()

    def markers(self, target, ee, force, band) -> None:
        """The target (hidden when NaN), the trail of ``ee``, the force arrow (N, drawn from
        the end effector at ``ARROW_SCALE`` m/N) and its band (a box around its tip).

        Args:
            target: (3,) the target position, m, world frame (NaN: none, hidden).
            ee: (3,) the end effector's position, m, world frame (NaN: no trail point, no
                arrow).
            force: (3,) the external force, N, world frame (NaN: no arrow).
            band: (3,) the force's band per axis, N (NaN: no box); the box's half sizes are
                ``ARROW_SCALE`` times it.
        """
        if np.all(np.isfinite(target)):
            self.target.position = np.asarray(target, float)
            self.target.visible = True
        else:
            self.target.visible = False
        self._frames += 1
        if np.all(np.isfinite(ee)):
            self.trail.append(np.asarray(ee, float))
            if self._frames % 3 == 0 and len(self.trail) > 1:  # 10 Hz
                pts = np.array(self.trail, dtype=np.float32)
                self._trail.points = np.stack([pts[:-1], pts[1:]], axis=1)
                self._trail.visible = True
        shown = bool(np.all(np.isfinite(force)) and np.all(np.isfinite(ee)))
        self.arrow.visible = shown
        self.band.visible = shown and bool(np.all(np.isfinite(band)))
        if shown:
            tip = np.asarray(ee) + ARROW_SCALE * np.asarray(force)
            self.arrow.points = np.array([[ee, tip]], dtype=np.float32)
            if self.band.visible:
                size = 2 * ARROW_SCALE * np.maximum(np.asarray(band, float), 1e-4)
                self.band.position = tip
                self.band.dimensions = tuple(float(x) for x in size)


__all__ = ["ARROW_SCALE", "RobotScene", "geom_color", "geom_mesh"]
