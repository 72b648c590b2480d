"""Which joints of a model are current-controlled, and the model reduced to them.

jaxcomp calibrates and controls the current-controlled joints of an arm. By default these are
the hinge joints that no equality constraint couples to another joint (a gripper's coupled
fingers are held by their own position servo). Slide joints, coupled joints, ball joints and any
joint a user leaves out are *held*: welded in the reduced model at their held position, the
model's ``qpos0`` moved inside the joint's limits. The joints of a mobile base (``BASE_JOINTS``)
are kept as they are.

Overrides, strongest first: the ``joints`` argument (CLI ``--joints``), then the model's
``<custom><text name="jaxcomp_joints" data="name name ..."/>``.

The end-effector site is the model's ``jaxcomp_end_effector`` custom text, else a site called
``end_effector``, else the ``site`` argument (CLI ``--site``), else a site ``end_effector``
added at the origin of the last body of the chain of current-controlled joints.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from jaxcomp.errors import ModelError

#: Joints of a mobile base: kept in the reduced model, never current-controlled.
BASE_JOINTS = ("base_x", "base_y", "base_yaw")
#: Name of the site added when a model names no end effector.
ADDED_SITE = "end_effector"
#: Held positions are moved this fraction of the joint's range inside its limits.
LIMIT_MARGIN = 0.05
#: kg: a current-controlled joint must move at least this much mass.
MIN_MOVED_MASS = 1e-6

_JOINT_KINDS = {
    mujoco.mjtJoint.mjJNT_FREE: "free",
    mujoco.mjtJoint.mjJNT_BALL: "ball",
    mujoco.mjtJoint.mjJNT_SLIDE: "slide",
    mujoco.mjtJoint.mjJNT_HINGE: "hinge",
}


@dataclass(frozen=True)
class Reduction:
    """How a model file becomes jaxcomp's robot: joints welded, a site added.

    Attributes:
        held: {joint name: held position}, rad (hinge) or m (slide); ball joints hold qpos0.
        site: the end-effector site's name.
        add_site_body: body name the site is added to (at its origin), or None when the model
            has the site.
        controlled: names of the current-controlled joints, model order.
        declared: the joints the model itself current-controls (its ``jaxcomp_joints``, else
            the default rule): what per-joint custom data of the model is listed for.
    """

    held: dict[str, float] = field(default_factory=dict)
    site: str = ADDED_SITE
    add_site_body: str | None = None
    controlled: tuple[str, ...] = ()
    declared: tuple[str, ...] = ()

    @property
    def changes_model(self) -> bool:
        return bool(self.held) or self.add_site_body is not None


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(model, kind, i) or f"{kind.name[6:].lower()}{i}"


def _custom_text(model: mujoco.MjModel, name: str) -> str | None:
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        return None
    adr, size = model.text_adr[i], model.text_size[i]
    return bytes(model.text_data[adr : adr + size]).decode().rstrip("\x00")


def coupled_joints(model: mujoco.MjModel) -> set[int]:
    """Joint ids that an active equality constraint ties to another joint (joint equalities,
    and tendon equalities through the joints of fixed tendons).

    Args:
        model: a compiled ``mujoco.MjModel``.

    Returns:
        The joint ids.
    """
    out: set[int] = set()
    for e in range(model.neq):
        if not model.eq_active0[e]:
            continue
        kind = model.eq_type[e]
        if kind == mujoco.mjtEq.mjEQ_JOINT:
            out.add(int(model.eq_obj1id[e]))
            if model.eq_obj2id[e] >= 0:
                out.add(int(model.eq_obj2id[e]))
        elif kind == mujoco.mjtEq.mjEQ_TENDON:
            for t in (model.eq_obj1id[e], model.eq_obj2id[e]):
                if t < 0:
                    continue
                adr, num = model.tendon_adr[t], model.tendon_num[t]
                for w in range(adr, adr + num):
                    if model.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT:
                        out.add(int(model.wrap_objid[w]))
    return out


def held_position(model: mujoco.MjModel, j: int) -> float:
    """qpos0 of a hinge or slide joint moved inside its limits by ``LIMIT_MARGIN`` of its range.

    Args:
        model: a compiled ``mujoco.MjModel``.
        j: the joint's id.

    Returns:
        The held position, rad (hinge) or m (slide).
    """
    q = float(model.qpos0[model.jnt_qposadr[j]])
    if not model.jnt_limited[j]:
        return q
    lo, hi = (float(x) for x in model.jnt_range[j])
    margin = LIMIT_MARGIN * (hi - lo)
    return float(np.clip(q, lo + margin, hi - margin)) if hi - lo > 2 * margin else (lo + hi) / 2


def _check_joint_names(names: Sequence[str], known: Sequence[str], source: str) -> None:
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ModelError(
            f"{source} names unknown joint(s) {', '.join(unknown)}; joints: {', '.join(known)}"
        )
    dup = sorted({n for n in names if list(names).count(n) > 1})
    if dup:
        raise ModelError(f"{source} names joint(s) {', '.join(dup)} more than once")


def plan_reduction(
    model: mujoco.MjModel, joints: Sequence[str] | None = None, site: str | None = None
) -> Reduction:
    """The ``Reduction`` of a compiled model (see the module docstring).

    Args:
        model: the compiled model file (``mujoco.MjModel``), not yet reduced.
        joints: names of the joints to current-control (CLI ``--joints``); None: the model's.
        site: the end-effector site's name (CLI ``--site``), used when the model names none.

    Returns:
        The ``Reduction``.

    Raises:
        ModelError: a free joint; unknown or repeated joint names, or listed joints that cannot
            be current-controlled; no joint to current-control; a joint that moves no mass; an
            end-effector site the model does not have.
    """
    names = [_name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
    kinds = [_JOINT_KINDS[mujoco.mjtJoint(int(t))] for t in model.jnt_type]
    free = [n for n, k in zip(names, kinds, strict=True) if k == "free"]
    if free:
        raise ModelError(
            f"joint {free[0]} (free) is a free joint: jaxcomp needs a fixed-base arm (remove the "
            "freejoint so the base is welded to the world)"
        )
    if (text := _custom_text(model, "jaxcomp_joints")) is not None:
        listed = text.split()
        _check_joint_names(listed, names, "the model's jaxcomp_joints")
        declared, source = set(listed), "the model's jaxcomp_joints"
    else:
        coupled = coupled_joints(model)
        declared = {
            n
            for j, (n, k) in enumerate(zip(names, kinds, strict=True))
            if k == "hinge" and j not in coupled and n not in BASE_JOINTS
        }
        source = None
    chosen = declared
    if joints is not None:
        _check_joint_names(joints, names, "--joints")
        chosen, source = set(joints), "--joints"
    bad = sorted(
        n for n in chosen if kinds[names.index(n)] not in ("hinge", "slide") or n in BASE_JOINTS
    )
    if bad:
        raise ModelError(
            f"{source} lists joint(s) {', '.join(bad)} that cannot be current-controlled "
            "(only hinge and slide joints of the arm can)"
        )
    if not names:
        raise ModelError("the model has no joints: nothing to move or identify")
    if not chosen and not any(n in BASE_JOINTS for n in names):  # a bare base has none
        described = ", ".join(f"{n} ({k})" for n, k in zip(names, kinds, strict=True)) or "none"
        raise ModelError(
            "no joints to current-control: jaxcomp needs at least one hinge joint that no "
            f"equality constraint couples to another; joints: {described}"
        )
    controlled = tuple(n for n in names if n in chosen)
    held = {}
    for j, n in enumerate(names):
        if n in chosen or n in BASE_JOINTS:
            continue
        held[n] = held_position(model, j) if kinds[j] in ("hinge", "slide") else 0.0
    _check_moved_mass(model, [names.index(n) for n in controlled], names)
    site_name, add_body = _end_effector(model, [names.index(n) for n in controlled], site)
    return Reduction(
        held=held,
        site=site_name,
        add_site_body=add_body,
        controlled=controlled,
        declared=tuple(n for n in names if n in declared),
    )


def as_is(model: mujoco.MjModel) -> Reduction:
    """The identity ``Reduction`` of a model used unchanged: every joint but a mobile base's is
    current-controlled; the site is ``jaxcomp_end_effector`` else ``end_effector``.

    Args:
        model: a compiled ``mujoco.MjModel``.

    Returns:
        The ``Reduction``, welding nothing and adding no site.
    """
    names = [_name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
    site = _custom_text(model, "jaxcomp_end_effector") or ADDED_SITE
    arm = tuple(n for n in names if n not in BASE_JOINTS)
    return Reduction(site=site, controlled=arm, declared=arm)


def _subtree_mass(model: mujoco.MjModel) -> np.ndarray:
    mass = model.body_mass.copy()
    for b in range(model.nbody - 1, 0, -1):
        mass[model.body_parentid[b]] += mass[b]
    return mass


def _check_moved_mass(model: mujoco.MjModel, controlled: list[int], names: list[str]) -> None:
    mass = _subtree_mass(model)
    for j in controlled:
        if mass[model.jnt_bodyid[j]] < MIN_MOVED_MASS:
            body = _name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[j]))
            raise ModelError(
                f"joint {names[j]!r} moves no mass: body {body!r} and the bodies below it have "
                "no mass (give them inertials, or leave the joint out with --joints)"
            )


def _end_effector(
    model: mujoco.MjModel, controlled: list[int], site: str | None
) -> tuple[str, str | None]:
    sites = [_name(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in range(model.nsite)]
    named = _custom_text(model, "jaxcomp_end_effector")
    if named:
        if named not in sites:
            raise ModelError(
                f"the model's jaxcomp_end_effector names site {named!r}, which it does not have; "
                f"sites: {', '.join(sites) or 'none'}"
            )
        return named, None
    if ADDED_SITE in sites:
        return ADDED_SITE, None
    if site is not None:
        if site not in sites:
            raise ModelError(f"unknown site {site!r} (--site); sites: {', '.join(sites) or 'none'}")
        return site, None
    if not controlled:  # a bare mobile base: no arm, no end effector
        return ADDED_SITE, None
    # the deepest body holding a controlled joint, then down while the chain does not branch
    depth = np.zeros(model.nbody, int)
    for b in range(1, model.nbody):
        depth[b] = depth[model.body_parentid[b]] + 1
    body = max((int(model.jnt_bodyid[j]) for j in controlled), key=lambda b: (depth[b], b))
    while True:
        children = [c for c in range(1, model.nbody) if model.body_parentid[c] == body]
        if len(children) != 1:
            break
        body = children[0]
    return ADDED_SITE, _name(model, mujoco.mjtObj.mjOBJ_BODY, body)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def _weld(spec: mujoco.MjSpec, model: mujoco.MjModel, joint: str, q: float) -> None:
    """Remove ``joint`` from ``spec``, fixing its body where the joint puts it at ``q``."""
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)
    b = int(model.jnt_bodyid[j])
    pos, quat = model.body_pos[b].copy(), model.body_quat[b].copy()
    kind = model.jnt_type[j]
    anchor, axis = model.jnt_pos[j], model.jnt_axis[j]
    if kind == mujoco.mjtJoint.mjJNT_HINGE:
        angle = q - float(model.qpos0[model.jnt_qposadr[j]])
        turn = np.zeros(4)
        mujoco.mju_axisAngle2Quat(turn, axis, angle)
        # body frame' = body frame * T(anchor) R(turn) T(-anchor)
        shift = np.zeros(3)
        mujoco.mju_rotVecQuat(shift, -anchor, turn)
        local = anchor + shift
        world_shift = np.zeros(3)
        mujoco.mju_rotVecQuat(world_shift, local, quat)
        pos, quat = pos + world_shift, _quat_mul(quat, turn)
    elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
        delta = np.zeros(3)
        mujoco.mju_rotVecQuat(delta, axis * (q - float(model.qpos0[model.jnt_qposadr[j]])), quat)
        pos = pos + delta
    body = spec.body(_name(model, mujoco.mjtObj.mjOBJ_BODY, b))
    body.pos = pos
    body.quat = quat
    body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    spec.delete(spec.joint(joint))


def _uses(obj, names: set[str]) -> bool:
    return any(getattr(obj, a, None) in names for a in ("target", "name1", "name2", "objname"))


def reduce_spec(spec: mujoco.MjSpec, model: mujoco.MjModel, reduction: Reduction) -> None:
    """Apply ``reduction`` to ``spec`` (compiled as ``model``) in place: weld the held joints,
    drop what refers to them (equalities, tendons, actuators, sensors), rewrite keyframes to the
    kept joints, add the end-effector site where needed.

    Args:
        spec: the model file's ``mujoco.MjSpec``, edited in place.
        model: ``spec`` compiled, unreduced (joint ids, positions and keyframes).
        reduction: what to weld and add (``plan_reduction``).
    """
    held = set(reduction.held)
    if held:
        dropped_tendons = set()
        for t in list(spec.tendons):
            if _tendon_joints(model, t.name) & held:
                dropped_tendons.add(t.name)
        gone = held | dropped_tendons
        for group in (spec.equalities, spec.actuators, spec.sensors):
            for obj in list(group):
                if _uses(obj, gone):
                    spec.delete(obj)
        for name in dropped_tendons:
            spec.delete(spec.tendon(name))
        for joint, q in reduction.held.items():
            _weld(spec, model, joint, q)
        kept = [
            j for j in range(model.njnt) if _name(model, mujoco.mjtObj.mjOBJ_JOINT, j) not in held
        ]
        qadr = np.concatenate(
            [np.arange(model.jnt_qposadr[j], model.jnt_qposadr[j] + _nq(model, j)) for j in kept]
        )
        vadr = np.concatenate(
            [np.arange(model.jnt_dofadr[j], model.jnt_dofadr[j] + _nv(model, j)) for j in kept]
        )
        for k, key in enumerate(spec.keys):
            key.qpos = model.key_qpos[k][qadr].tolist()
            key.qvel = model.key_qvel[k][vadr].tolist()
            key.act = []
            key.ctrl = []
    if reduction.add_site_body is not None:
        spec.body(reduction.add_site_body).add_site(
            name=reduction.site, pos=[0.0, 0.0, 0.0], size=[0.005, 0, 0], rgba=[0.9, 0.2, 0.1, 1]
        )


def _nq(model: mujoco.MjModel, j: int) -> int:
    return {0: 7, 1: 4}.get(int(model.jnt_type[j]), 1)


def _nv(model: mujoco.MjModel, j: int) -> int:
    return {0: 6, 1: 3}.get(int(model.jnt_type[j]), 1)


def _tendon_joints(model: mujoco.MjModel, tendon: str) -> set[str]:
    t = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TENDON, tendon)
    if t < 0:
        return set()
    adr, num = model.tendon_adr[t], model.tendon_num[t]
    return {
        _name(model, mujoco.mjtObj.mjOBJ_JOINT, int(model.wrap_objid[w]))
        for w in range(adr, adr + num)
        if model.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT
    }
