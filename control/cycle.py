"""The work of one control cycle once its state arrived (``Cycle``).

The base odometry turns the target into the arm frame (position; velocity relative to the
moving arm base; acceleration with the base's acceleration neglected); the controller gives
the command; the watchdog checks it; the base follower's twist goes to the base; one sample is
recorded (``run_recording``); the tracking error |ee - target| (world, m) is accumulated.

Frames (``mount``): the trajectory is in the base frame in guidance mode, in the world in
tracking mode; the controller works in the arm frame. The frame maths is done on Python floats
and written straight into the controller's packed input: no small numpy arrays per cycle.
"""

from __future__ import annotations

import math

import numpy as np

from jaxcomp.control.mount import ArmMount, rz
from jaxcomp.hardware.interface import ArmState


class Cycle:
    """The work of one cycle after its state arrived (see the module doc).

    Args:
        law: the ``law_adapter.LawAdapter`` (its ``target`` is written here).
        wd: the run's ``Watchdog``.
        traj: the ``Trajectory``, in the mode's frame (t in s from the start).
        t0: s, the state time of the start.
        base: the ``Base``, or None (arm alone).
        follower: the ``BaseFollower``, or None.
        mount: the ``ArmMount``.
        guidance: guidance mode (trajectory in the base frame), else tracking (world).
        desired_b: (3,) m, base frame: where the base keeps the end effector (tracking).
        recorder: the run's ``run_recording.Recorder`` (set before the first call).
        compensate: give the controller the target's velocity relative to the moving base.

    Attributes:
        sq_sum: m^2, sum of the squared tracking errors. max_err, last_err: m. samples: count.
    """

    def __init__(
        self,
        law,
        wd,
        traj,
        t0,
        base,
        follower,
        mount: ArmMount,
        guidance,
        desired_b,
        recorder,
        compensate,
    ):
        self.law, self.wd, self.traj, self.t0 = law, wd, traj, t0
        self.base, self.follower, self.mount = base, follower, mount
        self.guidance, self.desired_b = guidance, desired_b
        self.recorder, self.compensate = recorder, compensate
        self._pm = tuple(float(v) for v in mount.position)
        self._rm = tuple(float(v) for v in mount.rotation.ravel())  # row-major
        self._pivot = (float(mount.pivot[0]), float(mount.pivot[1]))
        self._desired = tuple(float(v) for v in desired_b)
        self.sq_sum, self.max_err, self.last_err, self.samples = 0.0, 0.0, math.nan, 0
        self.rot_b = None  # target orientation of the end effector in the base frame (guidance)
        self.rot_w = None  # ... in the world (tracking)
        self._target_w = (0.0, 0.0, 0.0)  # the last target, world m

    @property
    def target_w(self) -> np.ndarray:
        """(3,) m, the last target in the world."""
        return np.array(self._target_w)

    def hold_orientation(self, rot_a: np.ndarray, pose0: np.ndarray) -> None:
        """Keep the end effector's start orientation fixed in the mode's frame (base frame in
        guidance, world in tracking).

        Args:
            rot_a: (3, 3), the end effector's orientation at the start, arm frame.
            pose0: the base's start pose (x m, y m, yaw rad).
        """
        rot_b = self.mount.rotation @ rot_a
        if self.guidance:
            self.rot_b = rot_b
        else:
            self.rot_w = rz(float(pose0[2])) @ rot_b

    def rot(self, yaw: float) -> np.ndarray | None:
        """The target orientation now.

        Args:
            yaw: rad, the base's yaw.

        Returns:
            (3, 3), arm frame; None without an orientation task.
        """
        rm = self.mount.rotation
        if self.rot_b is not None:
            return rm.T @ self.rot_b
        if self.rot_w is not None:
            return rm.T @ (rz(yaw).T @ self.rot_w)
        return None

    def targets(self, t: float, px, py, yaw, vx, vy, wz, compensate: bool):
        """Write the target at time t into the controller's input (``law.target``, arm
        frame: pos m, vel m/s relative to the moving arm base when ``compensate``, acc m/s^2).

        Args:
            t: s from the start.
            px: m, the base's odometry x (world frame).
            py: m, its odometry y.
            yaw: rad, its odometry yaw.
            vx: m/s, its twist's x (base frame).
            vy: m/s, its twist's y.
            wz: rad/s, its yaw rate.
            compensate: subtract the base's velocity at the target point.

        Returns:
            (target in the base frame (3 floats, m), in the world (3 floats, m), cos yaw,
            sin yaw, the base frame's origin x, y in the world (m)).
        """
        sample = self.traj(t)
        (p0, p1, p2), (v0, v1, v2), (a0, a1, a2) = (
            sample.pos.tolist(),
            sample.vel.tolist(),
            sample.acc.tolist(),
        )
        c, s = math.cos(yaw), math.sin(yaw)
        qx, qy = self._pivot  # base origin in the world: (px, py, 0) + pivot - Rz pivot
        ox, oy = px + qx - (c * qx - s * qy), py + qy - (s * qx + c * qy)
        if self.guidance:  # the trajectory is in the base frame
            tb = (p0, p1, p2)
            tw = (ox + c * p0 - s * p1, oy + s * p0 + c * p1, p2)
        else:  # in the world: to the base frame (Rz^T)
            tw = (p0, p1, p2)
            dx, dy = p0 - ox, p1 - oy
            tb = (c * dx + s * dy, -s * dx + c * dy, p2)
            v0, v1 = c * v0 + s * v1, -s * v0 + c * v1
            a0, a1 = c * a0 + s * a1, -s * a0 + c * a1
            if compensate:  # minus the base's velocity at the target point (base frame)
                v0 -= vx - wz * tb[1]
                v1 -= vy + wz * tb[0]
        m, (m0, m1, m2) = self._rm, self._pm  # arm frame: Rm^T (x_b - p_m)
        e0, e1, e2 = tb[0] - m0, tb[1] - m1, tb[2] - m2
        self.law.target[:] = (
            m[0] * e0 + m[3] * e1 + m[6] * e2,
            m[1] * e0 + m[4] * e1 + m[7] * e2,
            m[2] * e0 + m[5] * e1 + m[8] * e2,
            m[0] * v0 + m[3] * v1 + m[6] * v2,
            m[1] * v0 + m[4] * v1 + m[7] * v2,
            m[2] * v0 + m[5] * v1 + m[8] * v2,
            m[0] * a0 + m[3] * a1 + m[6] * a2,
            m[1] * a0 + m[4] * a1 + m[7] * a2,
            m[2] * a0 + m[5] * a1 + m[8] * a2,
        )
        return tb, tw, c, s, ox, oy

    def first_command(self, state: ArmState, pose0: np.ndarray) -> np.ndarray:
        """The command at the start, with no side effect but the controller's input (the
        set-up's check).

        Args:
            state: the start state (t = 0).
            pose0: the base's start pose (x m, y m, yaw rad), the base at rest.

        Returns:
            (n,) A or rad/s.
        """
        px, py, yaw = (float(v) for v in pose0)
        self.targets(0.0, px, py, yaw, 0.0, 0.0, 0.0, False)
        if self.rot_b is not None or self.rot_w is not None:
            self.law.set_rot(self.rot(yaw))
        return self.law.run(state.q, state.dq, state.current)[0]

    def wrench_world(self, c: float, s: float) -> tuple[float, ...]:
        """The law's external force estimate (arm frame) in the world.

        Args:
            c, s: cos and sin of the base's yaw.

        Returns:
            force (3) N | band (3) N, world frame; the band is the world-axis box around the
            rotated one (|R| b, R = Rz(yaw) Rm).
        """
        f0, f1, f2, b0, b1, b2 = self.law.estimate[self.law.n :].tolist()
        m = self._rm
        r00, r01, r02 = c * m[0] - s * m[3], c * m[1] - s * m[4], c * m[2] - s * m[5]
        r10, r11, r12 = s * m[0] + c * m[3], s * m[1] + c * m[4], s * m[2] + c * m[5]
        r20, r21, r22 = m[6], m[7], m[8]
        return (
            r00 * f0 + r01 * f1 + r02 * f2,
            r10 * f0 + r11 * f1 + r12 * f2,
            r20 * f0 + r21 * f1 + r22 * f2,
            abs(r00) * b0 + abs(r01) * b1 + abs(r02) * b2,
            abs(r10) * b0 + abs(r11) * b1 + abs(r12) * b2,
            abs(r20) * b0 + abs(r21) * b1 + abs(r22) * b2,
        )

    def __call__(self, state: ArmState) -> np.ndarray:
        """The cycle's work for ``state``: targets, command, checks, base twist, one sample.

        Args:
            state: the arm's state just received.

        Returns:
            (n,) the command, A or rad/s (checked by the watchdog).
        """
        px, py, yaw, vx, vy, wz = self._odometry(state.t)
        q = state.q
        tb, tw, c, s, ox, oy = self.targets(
            state.t - self.t0, px, py, yaw, vx, vy, wz, self.compensate
        )
        if self.rot_b is not None or self.rot_w is not None:
            self.law.set_rot(self.rot(yaw))
        cmd, ee_a = self.law.run(q, state.dq, state.current)
        self.wd.check_command(cmd, state.t)
        m, (m0, m1, m2) = self._rm, self._pm  # ee in the base frame: p_m + Rm ee_a
        a0, a1, a2 = ee_a.tolist()
        eb = (
            m0 + m[0] * a0 + m[1] * a1 + m[2] * a2,
            m1 + m[3] * a0 + m[4] * a1 + m[5] * a2,
            m2 + m[6] * a0 + m[7] * a1 + m[8] * a2,
        )
        if self.follower is not None:
            p_d = tb if self.guidance else self._desired
            self.base.send_twist(self.follower.twist(eb, p_d, q))
        self._target_w = tw
        frames = (*tw, ox + c * eb[0] - s * eb[1], oy + s * eb[0] + c * eb[1], eb[2], px, py, yaw)
        if self.law.estimates:
            frames += self.wrench_world(c, s)
            model = self.law.estimate[: self.law.n]
        else:
            model = None
        self.recorder.add(state.t, q, state.dq, state.current, cmd, frames, model)
        self._track(eb, tb, state.t - self.t0)
        return cmd

    def _odometry(self, t: float) -> tuple[float, ...]:
        """The base's pose and twist (x, y, yaw, vx, vy, wz), checked; zeros without a base."""
        if self.base is None:
            return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        odom = self.base.odometry()
        pose, twist = odom.pose, odom.twist
        self.wd.check_odometry(pose, twist, t)
        return (*pose.tolist(), *twist.tolist())

    def _track(self, eb, tb, t: float) -> None:
        """Accumulate the tracking error |ee - target| (m) and let the watchdog check it."""
        d0, d1, d2 = eb[0] - tb[0], eb[1] - tb[1], eb[2] - tb[2]
        e2 = d0 * d0 + d1 * d1 + d2 * d2
        self.sq_sum += e2
        self.last_err = math.sqrt(e2)
        if self.last_err > self.max_err:
            self.max_err = self.last_err
        self.samples += 1
        self.wd.check_error(self.last_err, t)


__all__ = ["Cycle"]
