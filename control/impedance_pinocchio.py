"""The impedance law in pinocchio + numpy: the reference and latency baseline of the jitted
JAX controller (``control.impedance``), same law, same arguments, same results.

The pinocchio model is built from ``jaxcomp.urdf.to_urdf`` of the identified (COM-corrected)
inertials; the law's terms are ``control.impedance_terms``' (with numpy) and the current is
``jaxcomp.current.friction_current``. Frames: the arm's base frame; m, rad, s, N, A.
"""

from __future__ import annotations

import numpy as np

from jaxcomp.control.external_force import external_force
from jaxcomp.control.impedance import ImpedanceLaw
from jaxcomp.control.impedance_io import Diagnostics, live_gains, pack_diagnostics
from jaxcomp.control.impedance_terms import clip_error, limit_current, orientation_error
from jaxcomp.current import friction_current
from jaxcomp.errors import InputError


class ImpedanceControllerPinocchio(ImpedanceLaw):
    """The same control law in pinocchio + numpy (reference and latency baseline).

    ``step`` takes and returns numpy arrays, same arguments and results as
    ``ImpedanceController.step``. The pinocchio model is built from ``jaxcomp.urdf.to_urdf``
    of the identified (COM-corrected) inertials.

    Args:
        robot, params, gains, site: see ``impedance.ImpedanceLaw``.

    Raises:
        InputError: see ``impedance.ImpedanceLaw``; or a pinocchio model whose joints are not
            the robot's.
    """

    def _build(self) -> None:
        """The pinocchio model of the identified inertials, its frame and joint order."""
        import pinocchio as pin

        from jaxcomp.urdf import to_urdf

        robot, gains, site, res = self.robot, self.gains, self.site, self.resolved
        self._pin = pin
        self.model = pin.buildModelFromXML(to_urdf(res.tree, res.inertial, robot.name))
        self.model.gravity.linear = res.gravity_vector
        self.data = self.model.createData()
        names = list(self.model.names)[1:]
        if sorted(names) != sorted(robot.joint_names) or self.model.nq != self.n:
            raise InputError(f"pinocchio model of {robot.name} does not match its joints")
        self._perm = np.array([names.index(nm) for nm in robot.joint_names])
        self._identity = bool(np.all(self._perm == np.arange(self.n)))
        self._frame = self.model.getFrameId(site)
        self._lwa = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        self._eye = gains.singularity_damping * np.eye(3)
        self._lower = np.tril_indices(self.n, -1)

    def _to_pin(self, x: np.ndarray) -> np.ndarray:
        if self._identity:
            return x
        out = np.empty(self.n)
        out[self._perm] = x
        return out

    def _from_pin(self, x: np.ndarray) -> np.ndarray:
        return x if self._identity else x[..., self._perm]

    def step(
        self,
        q,
        dq,
        target_pos,
        target_vel,
        target_acc,
        prev_current,
        target_rot=None,
        current=None,
        live=None,
    ) -> tuple[np.ndarray, Diagnostics]:
        """One step on numpy inputs.

        Args:
            q, dq, target_pos, target_vel, target_acc, prev_current, target_rot, current,
                live: as ``ImpedanceController.step``'s (rad, rad/s, m, m/s, m/s^2, A; arm
                base frame).

        Returns:
            (current (n,) A, Diagnostics), numpy.
        """
        pin, pm, pd, g, res = self._pin, self.model, self.data, self.gains, self.resolved
        qp, vp = self._to_pin(np.asarray(q, float)), self._to_pin(np.asarray(dq, float))
        grav = self._from_pin(pin.computeGeneralizedGravity(pm, pd, qp))
        mass = pin.crba(pm, pd, qp)  # upper triangle filled
        mass[self._lower] = mass.T[self._lower]
        if not self._identity:
            mass = mass[np.ix_(self._perm, self._perm)]
        jac6 = self._from_pin(pin.computeFrameJacobian(pm, pd, qp, self._frame, self._lwa))
        frame = pd.oMf[self._frame]
        pos, jac = frame.translation.copy(), jac6[:3]
        error, clipped = clip_error(target_pos - pos, g.deadband, g.error_clip, np)
        if live is None:
            live = live_gains(g.stiffness, g.damping, True)
        k_d, d_d, compensate = live[0:3], live[3:6], live[6]
        force = k_d * error + d_d * (target_vel - jac @ dq)
        k_n, d_n = res.joint.stiffness, res.joint.damping
        tau2 = k_n * (res.joint.posture - q) - d_n * dq
        if g.orientation:
            jac_w = jac6[3:]
            e_o = orientation_error(frame.rotation, np.asarray(target_rot), np)
            moment = np.asarray(g.orientation_stiffness) * e_o
            moment = moment - np.asarray(g.orientation_damping) * (jac_w @ dq)
            tau2 = tau2 + jac_w.T @ moment
        x = np.linalg.solve(mass, np.concatenate([jac.T, tau2[:, None]], axis=1))
        lam = np.linalg.inv(jac @ x[:, :3] + self._eye)
        f_total = force - lam @ (jac @ x[:, 3])
        if g.feedforward:
            jac_bar = x[:, :3] @ lam
            pin.computeJointJacobiansTimeVariation(pm, pd, qp, vp)
            jac_dot = self._from_pin(
                pin.getFrameJacobianTimeVariation(pm, pd, self._frame, self._lwa)[:3]
            )
            cor = pin.computeCoriolisMatrix(pm, pd, qp, vp)
            if not self._identity:
                cor = cor[np.ix_(self._perm, self._perm)]
            v_bar = jac_bar @ target_vel
            ff = lam @ target_acc + jac_bar.T @ (cor @ v_bar) - lam @ (jac_dot @ v_bar)
            force, f_total = force + ff, f_total + ff
        tau_motion = jac.T @ f_total + tau2
        tau = tau_motion + grav
        tau_rest = tau_motion if g.friction_direction == "motion" else tau
        ratio, friction, threshold = res.ratio, res.friction, g.friction_threshold
        raw = friction_current(
            tau, tau_rest, dq, ratio, compensate * friction, threshold, g.friction_band, np
        )
        prev = np.asarray(prev_current, float)
        cur, rate_limited, saturated = limit_current(
            raw, prev, g.max_current_step, res.joint.limit, np
        )
        measured = prev if current is None else np.asarray(current, float)
        estimate = external_force(jac, grav, dq, measured, ratio, friction, threshold, np)
        diag = pack_diagnostics(
            pos, error, force, tau, raw, rate_limited, saturated, clipped, estimate
        )
        return cur, diag


__all__ = ["ImpedanceControllerPinocchio"]
