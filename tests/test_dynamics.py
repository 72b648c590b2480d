"""JAX dynamics against MuJoCo and pinocchio on 1000 random poses, for three robots (and the
mobile manipulator for the one-pass function)."""

from functools import partial

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

import jaxcomp
from arms import branched_prismatic, offset_arm_7dof
from jaxcomp import components as cp
from jaxcomp import dynamics
from jaxcomp.urdf import to_urdf

N_POSES = 1000
TOL = 1e-9


def _with_sites(urdf: str, sites: dict[str, str], seed: int) -> mujoco.MjModel:
    """Compile URDF text in MuJoCo and add a site at a random offset on each named body."""
    rng = np.random.default_rng(seed)
    spec = mujoco.MjSpec.from_string(urdf)
    for site, body in sites.items():
        quat = Rotation.random(random_state=rng).as_quat(scalar_first=True)
        spec.body(body).add_site(name=site, pos=rng.uniform(-0.1, 0.1, 3), quat=quat)
    return spec.compile()


class Case:
    """A robot under test: jaxcomp Robot, MuJoCo model, pinocchio model with site frames."""

    def __init__(self, robot: jaxcomp.Robot, pin_model: pin.Model):
        self.robot = robot
        self.pm = pin_model
        names = list(pin_model.names)[1:]
        self.perm = np.array([names.index(n) for n in robot.joint_names])
        tree = robot.tree
        # add pinocchio frames for sites that the URDF did not carry
        for s, site in enumerate(tree.site_names):
            if pin_model.existFrame(site):
                continue
            body = tree.body_names[tree.site_body[s]]
            parent_frame = pin_model.getFrameId(body, pin.FrameType.BODY)
            joint = pin_model.frames[parent_frame].parentJoint
            placement = pin_model.frames[parent_frame].placement * pin.SE3(
                tree.site_rot[s], tree.site_pos[s]
            )
            pin_model.addFrame(
                pin.Frame(site, joint, parent_frame, placement, pin.FrameType.OP_FRAME)
            )
        self.pd = pin_model.createData()
        lo, hi = robot.joint_limits.T
        rng = np.random.default_rng(0)
        self.q = rng.uniform(np.maximum(lo, -3.0), np.minimum(hi, 3.0), (N_POSES, robot.nv))
        self.dq = rng.normal(0, 1.5, (N_POSES, robot.nv))
        self.ddq = rng.normal(0, 4.0, (N_POSES, robot.nv))
        sites = range(len(tree.site_names))

        def evaluate(q, dq, ddq):
            return (
                dynamics.gravity(tree, q),
                dynamics.mass_matrix(tree, q),
                dynamics.bias(tree, q, dq),
                jnp.stack([dynamics.site_jacobian(tree, q, s) for s in sites]),
                jnp.stack([dynamics.site_pose(tree, q, s)[0] for s in sites]),
                dynamics.kinematics_and_dynamics(tree, q, 0),  # the one-pass function, site 0
                dynamics.inverse_dynamics(tree, q, dq, ddq),
            )

        self.jax = jax.tree.map(np.asarray, jax.jit(jax.vmap(evaluate))(self.q, self.dq, self.ddq))
        self.kd = self.jax[5]  # fields (N_POSES, ...)

    def to_pin(self, x: np.ndarray) -> np.ndarray:
        out = np.zeros(self.pm.nq)
        out[self.perm] = x
        return out


def _gen3_lite() -> Case:
    robot = jaxcomp.load_robot("gen3_lite")
    return Case(robot, pin.buildModelFromXML(to_urdf(robot.tree)))


def _urdf_case(urdf: str, sites: dict[str, str], seed: int) -> Case:
    robot = jaxcomp.Robot(_with_sites(urdf, sites, seed), name="test")
    return Case(robot, pin.buildModelFromXML(urdf))


CASES = {
    "gen3_lite": _gen3_lite,
    "offset_arm_7dof": lambda: _urdf_case(offset_arm_7dof(), {"tip": "link7"}, 1),
    "branched_prismatic": lambda: _urdf_case(
        branched_prismatic(), {"left": "l3", "right": "r2"}, 2
    ),
}


# one worker computes each case, once (session: never torn down between its tests)
pytestmark = pytest.mark.xdist_group("dynamics")


@pytest.fixture(scope="session", params=list(CASES))
def case(request) -> Case:
    return CASES[request.param]()


def test_against_mujoco(case):
    m = case.robot.model
    d = mujoco.MjData(m)
    full_m = np.zeros((m.nv, m.nv))
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    g_ref = mujoco.MjData(m)
    for k in range(N_POSES):
        d.qpos[:], d.qvel[:] = case.q[k], case.dq[k]
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, full_m)
        g_ref.qpos[:] = case.q[k]
        mujoco.mj_forward(m, g_ref)  # zero velocity: qfrc_bias is gravity alone
        np.testing.assert_allclose(case.jax[0][k], g_ref.qfrc_bias, atol=TOL, rtol=0)
        np.testing.assert_allclose(case.jax[1][k], full_m, atol=TOL, rtol=0)
        np.testing.assert_allclose(case.jax[2][k], d.qfrc_bias, atol=TOL, rtol=0)
        tau = full_m @ case.ddq[k] + d.qfrc_bias
        np.testing.assert_allclose(case.jax[6][k], tau, atol=TOL, rtol=0)
        for s in range(m.nsite):
            mujoco.mj_jacSite(m, d, jacp, jacr, s)
            np.testing.assert_allclose(case.jax[3][k, s], np.vstack([jacp, jacr]), atol=TOL, rtol=0)
            np.testing.assert_allclose(case.jax[4][k, s], d.site_xpos[s], atol=TOL)
            if s == 0:
                kd = case.kd
                np.testing.assert_allclose(kd.gravity[k], g_ref.qfrc_bias, atol=TOL, rtol=0)
                np.testing.assert_allclose(kd.mass_matrix[k], full_m, atol=TOL, rtol=0)
                np.testing.assert_allclose(
                    kd.jacobian[k], np.vstack([jacp, jacr]), atol=TOL, rtol=0
                )
                np.testing.assert_allclose(kd.position[k], d.site_xpos[s], atol=TOL)
                np.testing.assert_allclose(kd.rotation[k].ravel(), d.site_xmat[s], atol=TOL)


def test_against_pinocchio(case):
    pm, pd, perm = case.pm, case.pd, case.perm
    frames = [pm.getFrameId(s) for s in case.robot.site_names]
    for k in range(N_POSES):
        q, v = case.to_pin(case.q[k]), case.to_pin(case.dq[k])
        np.testing.assert_allclose(
            case.jax[0][k], pin.computeGeneralizedGravity(pm, pd, q)[perm], atol=TOL, rtol=0
        )
        np.testing.assert_allclose(
            case.jax[2][k], pin.nonLinearEffects(pm, pd, q, v)[perm], atol=TOL, rtol=0
        )
        a = case.to_pin(case.ddq[k])
        np.testing.assert_allclose(
            case.jax[6][k], pin.rnea(pm, pd, q, v, a)[perm], atol=TOL, rtol=0
        )
        mass = pin.crba(pm, pd, q)
        mass = np.triu(mass) + np.triu(mass, 1).T
        np.testing.assert_allclose(case.jax[1][k], mass[np.ix_(perm, perm)], atol=TOL, rtol=0)
        np.testing.assert_allclose(
            case.kd.mass_matrix[k], mass[np.ix_(perm, perm)], atol=TOL, rtol=0
        )
        pin.computeJointJacobians(pm, pd, q)
        pin.updateFramePlacements(pm, pd)
        for s, f in enumerate(frames):
            jac = pin.getFrameJacobian(pm, pd, f, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
            np.testing.assert_allclose(case.jax[3][k, s], jac[:, perm], atol=TOL, rtol=0)
            np.testing.assert_allclose(case.jax[4][k, s], pd.oMf[f].translation, atol=TOL)
            if s == 0:
                kd = case.kd
                np.testing.assert_allclose(kd.jacobian[k], jac[:, perm], atol=TOL, rtol=0)
                np.testing.assert_allclose(kd.position[k], pd.oMf[f].translation, atol=TOL)
                np.testing.assert_allclose(kd.rotation[k], pd.oMf[f].rotation, atol=TOL)
                g_pin = pin.computeGeneralizedGravity(pm, pd, q)[perm]
                np.testing.assert_allclose(kd.gravity[k], g_pin, atol=TOL, rtol=0)


def test_gravity_grad_matches_finite_differences(case):
    tree = case.robot.tree
    q = jnp.asarray(case.q[3])
    weights = jnp.asarray(np.random.default_rng(5).normal(size=tree.nv))
    params = case.robot.nominal_params()

    @jax.jit
    def loss(mass, com):
        return weights @ dynamics.gravity(tree, q, params._replace(mass=mass, com=com))

    g_mass, g_com = jax.grad(loss, argnums=(0, 1))(params.mass, params.com)
    eps = 1e-6
    for grad, arg in ((g_mass, 0), (g_com, 1)):
        base = [np.asarray(params.mass), np.asarray(params.com)]
        fd = np.zeros(base[arg].shape)
        for idx in np.ndindex(fd.shape):
            plus = [b.copy() for b in base]
            minus = [b.copy() for b in base]
            plus[arg][idx] += eps
            minus[arg][idx] -= eps
            fd[idx] = (loss(*plus) - loss(*minus)) / (2 * eps)
        scale = np.maximum(np.abs(fd), 1e-3 * np.abs(fd).max())
        assert np.max(np.abs(np.asarray(grad) - fd) / scale) < 1e-6
        assert np.abs(fd).max() > 1e-3  # the check is not vacuous


def test_operational_space_against_pinocchio(case):
    """Lambda, mu (with C and J_dot from pinocchio) and the nullspace projector of Eq. (5)."""
    robot, pm, pd, perm = case.robot, case.pm, case.pd, case.perm
    site = robot.site_names[0]
    f = pm.getFrameId(site)
    for k in range(5):
        q, v = case.to_pin(case.q[k]), case.to_pin(case.dq[k])
        ops = robot.operational_space(case.q[k], case.dq[k], site)
        pin.computeJointJacobiansTimeVariation(pm, pd, q, v)
        pin.updateFramePlacements(pm, pd)
        frame = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        jac = pin.getFrameJacobian(pm, pd, f, frame)[:3][:, perm]
        jdot = pin.getFrameJacobianTimeVariation(pm, pd, f, frame)[:3][:, perm]
        mass = pin.crba(pm, pd, q)
        mass = (np.triu(mass) + np.triu(mass, 1).T)[np.ix_(perm, perm)]
        cor = pin.computeCoriolisMatrix(pm, pd, q, v)[np.ix_(perm, perm)]
        lam = np.linalg.inv(jac @ np.linalg.solve(mass, jac.T))
        jbar = np.linalg.solve(mass, jac.T) @ lam
        mu = (jbar.T @ cor - lam @ jdot) @ jbar
        np.testing.assert_allclose(ops.lam, lam, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(ops.mu, mu, rtol=1e-7, atol=1e-8)
        n = np.asarray(ops.nullspace)
        np.testing.assert_allclose(n @ n, n, atol=1e-9)
        # torques through N cause no task acceleration: J M^-1 N tau = 0
        tau = np.random.default_rng(k).normal(size=robot.nv)
        np.testing.assert_allclose(jac @ np.linalg.solve(mass, n @ tau), 0, atol=1e-9)


def test_coriolis_matrix_is_passive(case):
    tree = case.robot.tree
    q, dq = jnp.asarray(case.q[1]), jnp.asarray(case.dq[1])

    @jax.jit
    def terms(q, dq):
        _, mdot = jax.jvp(lambda x: dynamics.mass_matrix(tree, x), (q,), (dq,))
        return dynamics.coriolis_matrix(tree, q, dq), mdot, dynamics.coriolis(tree, q, dq)

    c, mdot, c_dq = terms(q, dq)
    skew = np.asarray(mdot - 2 * c)
    np.testing.assert_allclose(skew, -skew.T, atol=1e-10)
    np.testing.assert_allclose(c @ dq, c_dq, atol=1e-10)


def test_kinematics_and_dynamics_takes_params_and_gravity():
    """Runtime inertial parameters and gravity vector: the values of the separate functions,
    and gradients with respect to the parameters (against finite differences)."""
    robot = jaxcomp.load_robot("gen3_lite")
    tree = robot.tree
    nominal = robot.nominal_params()
    rng = np.random.default_rng(3)
    params = nominal._replace(
        mass=nominal.mass * rng.uniform(0.8, 1.2, tree.nb),
        com=nominal.com + rng.uniform(-0.01, 0.01, (tree.nb, 3)),
    )
    gvec = jnp.asarray([1.0, -2.0, -9.5])
    site = robot.site_index("end_effector")

    @jax.jit
    def fast(q, com):
        def run(c):
            return dynamics.kinematics_and_dynamics(tree, q, site, params._replace(com=c), gvec)

        def loss(c):
            g = run(c).gravity
            return g @ g

        pos, rot = dynamics.site_pose(tree, q, site)
        p = params._replace(com=com)
        want = (
            dynamics.gravity(tree, q, p, gvec),
            dynamics.site_jacobian(tree, q, site),
            pos,
            rot,
            dynamics.mass_matrix(tree, q, p),
        )
        return run(com), loss(com), jax.grad(loss)(com), want

    for q in rng.uniform(-2.5, 2.5, (3, tree.nv)):
        out, _, grad, want = fast(jnp.asarray(q), params.com)
        for a, b in zip(out, want, strict=True):
            np.testing.assert_allclose(a, b, atol=1e-12, rtol=0)
    eps, com = 1e-6, np.asarray(params.com)
    fd = np.zeros_like(com)
    for idx in np.ndindex(com.shape):
        plus, minus = com.copy(), com.copy()
        plus[idx] += eps
        minus[idx] -= eps
        fd[idx] = (fast(jnp.asarray(q), plus)[1] - fast(jnp.asarray(q), minus)[1]) / (2 * eps)
    np.testing.assert_allclose(grad, fd, atol=1e-6 * np.abs(fd).max())
    assert np.abs(fd).max() > 1e-3


def test_mobile_arm_against_mujoco():
    """Slides, three joints in one body, a jointless link at an offset, depth 9."""
    robot = jaxcomp.load_robot("mobile_gen3_lite")
    tree, m = robot.tree, robot.model
    lo, hi = robot.joint_limits.T
    rng = np.random.default_rng(4)
    q = rng.uniform(np.maximum(lo, -3.0), np.minimum(hi, 3.0), (30, tree.nv))
    dq, ddq = rng.normal(0, 1.5, (2, 30, tree.nv))

    site = robot.site_index("end_effector")
    kd = jax.jit(jax.vmap(lambda q: dynamics.kinematics_and_dynamics(tree, q, site)))(q)
    tau = jax.jit(jax.vmap(partial(dynamics.inverse_dynamics, tree)))(q, dq, ddq)
    d = mujoco.MjData(m)
    full_m = np.zeros((m.nv, m.nv))
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for k in range(len(q)):
        d.qpos[:], d.qvel[:] = q[k], dq[k]
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, full_m)
        mujoco.mj_jacSite(m, d, jacp, jacr, site)
        np.testing.assert_allclose(tau[k], full_m @ ddq[k] + d.qfrc_bias, atol=TOL, rtol=0)
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        np.testing.assert_allclose(kd.gravity[k], d.qfrc_bias, atol=TOL, rtol=0)
        np.testing.assert_allclose(kd.mass_matrix[k], full_m, atol=TOL, rtol=0)
        np.testing.assert_allclose(kd.jacobian[k], np.vstack([jacp, jacr]), atol=TOL, rtol=0)
        np.testing.assert_allclose(kd.position[k], d.site_xpos[site], atol=TOL)
        np.testing.assert_allclose(kd.rotation[k].ravel(), d.site_xmat[site], atol=TOL)


def test_sincos_matches_libm_and_differentiates():
    x = np.concatenate(
        [
            np.linspace(-20.0, 20.0, 100001),
            np.random.default_rng(6).uniform(-1e6, 1e6, 20000),
            [0.0, -0.0, np.pi / 2, -np.pi, 1e-300],
        ]
    )
    s, c = jax.jit(cp.sincos)(x)
    np.testing.assert_allclose(s, np.sin(x), atol=5e-16, rtol=0)
    np.testing.assert_allclose(c, np.cos(x), atol=5e-16, rtol=0)
    ds, dc = jax.jvp(cp.sincos, (0.7,), (1.0,))[1]
    assert ds == pytest.approx(np.cos(0.7), abs=1e-15)
    assert dc == pytest.approx(-np.sin(0.7), abs=1e-15)
