"""Arms jaxcomp was not built around, for the tests and ``any_arm_pipeline.py`` (seeded, random
sizes).

``serial_arm`` writes an MJCF serial arm: a base yaw joint, then pitch and roll joints in turn,
random link lengths and masses, effort limits about twice the worst static gravity torque.
Options add continuous joints, a two-finger gripper on slide joints coupled by an equality
constraint, keyframes, an ``end_effector`` site, and a second arm on the same base (a branched
tree). No option gives a site or keyframes unless asked.
"""

from __future__ import annotations

import numpy as np

#: Axis of joint k (in its body frame) after the base yaw: pitch, pitch, roll, pitch, roll ...
_AXES = ["0 1 0", "0 1 0", "1 0 0", "0 1 0", "1 0 0", "0 1 0"]


def _inertial(rng: np.random.Generator, mass: float, length: float) -> str:
    r = 0.03 + 0.02 * rng.random()
    along = mass * (3 * r**2 + length**2) / 12
    across = mass * r**2 / 2
    com = (0.5 * length + rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 0.0)
    return (
        f'<inertial pos="{com[0]:.4f} {com[1]:.4f} {com[2]:.4f}" mass="{mass:.4f}" '
        f'diaginertia="{across:.6f} {along:.6f} {along:.6f}"/>'
    )


def _chain(
    rng: np.random.Generator,
    prefix: str,
    n: int,
    scale: float,
    continuous: set[int],
    effort: float,
) -> tuple[str, str]:
    """(opening tags of the nested bodies, closing tags) of one arm's joints 1..n-1."""
    opening, closing = [], []
    for k in range(1, n):
        length = scale * rng.uniform(0.12, 0.3) if k < 3 else scale * rng.uniform(0.05, 0.12)
        mass = scale**2 * rng.uniform(0.3, 1.5) if k < 3 else scale**2 * rng.uniform(0.1, 0.5)
        axis = _AXES[(k - 1) % len(_AXES)]
        rng_attr = "" if k in continuous else f' range="{-2.4 + 0.2 * rng.random():.3f} 2.4"'
        offset = scale * (0.08 if k == 1 else rng.uniform(0.15, 0.3))
        pos = f"0 0 {offset:.4f}" if k == 1 else f"{offset:.4f} 0 0"
        opening.append(
            f'<body name="{prefix}link{k}" pos="{pos}">'
            f'<joint name="{prefix}j{k}" axis="{axis}"{rng_attr} '
            f'actuatorfrcrange="{-effort:.3f} {effort:.3f}"/>'
            f"{_inertial(rng, mass, length)}"
            f'<geom type="capsule" fromto="0 0 0 {length:.4f} 0 0" size="{0.02 * scale:.4f}"/>'
        )
        closing.append("</body>")
    return "".join(opening), "".join(closing)


def serial_arm(
    seed: int = 0,
    n: int = 6,
    *,
    scale: float = 1.0,
    continuous: tuple[int, ...] = (),
    gripper: bool = False,
    keyframes: bool = False,
    site: bool = False,
    branched: bool = False,
    effort: float | None = None,
) -> str:
    """MJCF text of a random serial arm with ``n`` joints (see the module docstring).

    ``scale`` multiplies lengths (masses by its square); ``continuous`` lists joint indices
    without limits (0 = the base yaw); ``effort`` N m for every joint (default from the size).
    """
    rng = np.random.default_rng(seed)
    effort = effort if effort is not None else 30.0 * scale**3 + 2.0
    yaw_range = "" if 0 in continuous else ' range="-2.8 2.8"'
    arm, close = _chain(rng, "", n, scale, set(continuous), effort)
    hand = ""
    if gripper:
        hand = (
            '<body name="hand" pos="0.05 0 0"><inertial pos="0.02 0 0" mass="0.08" '
            'diaginertia="2e-5 2e-5 2e-5"/><geom type="box" size="0.02 0.03 0.01"/>'
            '<body name="finger_l" pos="0.04 0.01 0"><joint name="finger_l" type="slide" '
            'axis="0 1 0" range="0 0.03" actuatorfrcrange="-5 5"/>'
            '<inertial pos="0.01 0 0" mass="0.02" '
            'diaginertia="1e-6 1e-6 1e-6"/><geom type="box" size="0.01 0.003 0.008"/></body>'
            '<body name="finger_r" pos="0.04 -0.01 0"><joint name="finger_r" type="slide" '
            'axis="0 -1 0" range="0 0.03" actuatorfrcrange="-5 5"/>'
            '<inertial pos="0.01 0 0" mass="0.02" '
            'diaginertia="1e-6 1e-6 1e-6"/><geom type="box" size="0.01 0.003 0.008"/></body>'
            + ('<site name="end_effector" pos="0.06 0 0"/>' if site else "")
            + "</body>"
        )
    elif site:
        hand = '<site name="end_effector" pos="0.05 0 0"/>'
    second = ""
    if branched:
        other, other_close = _chain(rng, "b_", max(n - 2, 2), scale, set(), effort)
        second = (
            '<body name="b_base" pos="0 0.3 0.05"><joint name="b_j0" axis="0 0 1" range="-2 2" '
            f'actuatorfrcrange="{-effort:.3f} {effort:.3f}"/>'
            f"{_inertial(rng, 0.5, 0.1)}{other}{other_close}</body>"
        )
    body = (
        f'<body name="link0" pos="0 0 0.05"><joint name="j0" axis="0 0 1"{yaw_range} '
        f'actuatorfrcrange="{-effort:.3f} {effort:.3f}"/>{_inertial(rng, 0.8 * scale**2, 0.1)}'
        f'<geom type="cylinder" size="{0.04 * scale:.4f} 0.04"/>{arm}{hand}{close}</body>'
    )
    equality = (
        '<equality><joint joint1="finger_l" joint2="finger_r" polycoef="0 1 0 0 0"/></equality>'
        if gripper
        else ""
    )
    nq = n + (len(serial_arm_branch_joints(n)) if branched else 0) + (2 if gripper else 0)
    keys = ""
    if keyframes:
        q = np.zeros(nq)
        if n >= 3:
            q[1], q[2] = 0.4, 0.9
        keys = f'<keyframe><key name="home" qpos="{" ".join(f"{v:.3f}" for v in q)}"/></keyframe>'
    return (
        f'<mujoco model="odd{seed}"><compiler angle="radian" autolimits="true"/>'
        '<option timestep="0.001" gravity="0 0 -9.81"/>'
        '<default><geom contype="0" conaffinity="0" density="0"/>'
        '<joint actuatorfrclimited="true"/></default>'
        f"<worldbody>{body}{second}</worldbody>{equality}{keys}</mujoco>"
    )


def serial_arm_branch_joints(n: int) -> list[str]:
    """Joint names of the second arm ``serial_arm(branched=True)`` adds."""
    return ["b_j0"] + [f"b_j{k}" for k in range(1, max(n - 2, 2))]


def serial_arm_urdf(seed: int = 0, n: int = 6, *, continuous: tuple[int, ...] = (0,)) -> str:
    """URDF text of a random serial arm like ``serial_arm`` (no sites, as URDFs have none):
    a base yaw joint, then pitch and roll joints in turn; ``continuous`` joints unlimited."""
    rng = np.random.default_rng(seed)
    axes = ["0 0 1"] + [_AXES[(k - 1) % len(_AXES)] for k in range(1, n)]
    effort = 32.0
    parts = [f'<robot name="odd_urdf{seed}">', '<link name="base"/>']
    parent = "base"
    for k in range(n):
        length = rng.uniform(0.12, 0.3) if 0 < k < 3 else rng.uniform(0.05, 0.12)
        mass = rng.uniform(0.3, 1.5) if k < 3 else rng.uniform(0.1, 0.5)
        r = 0.04
        along, across = mass * (3 * r**2 + length**2) / 12, mass * r**2 / 2
        com = (0.0, 0.0, 0.05) if k == 0 else (0.5 * length, 0.0, 0.0)
        xyz = (
            "0 0 0.05"
            if k == 0
            else ("0 0 0.08" if k == 1 else f"{rng.uniform(0.15, 0.3):.4f} 0 0")
        )
        kind = "continuous" if k in continuous else "revolute"
        limit = (
            f'<limit effort="{effort}" velocity="3"/>'
            if kind == "continuous"
            else f'<limit lower="-2.4" upper="2.4" effort="{effort}" velocity="3"/>'
        )
        parts += [
            f'<link name="link{k}"><inertial><origin xyz="{com[0]:.4f} {com[1]} {com[2]}"/>'
            f'<mass value="{mass:.4f}"/><inertia ixx="{across:.6f}" ixy="0" ixz="0" '
            f'iyy="{along:.6f}" iyz="0" izz="{along:.6f}"/></inertial></link>',
            f'<joint name="j{k}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="link{k}"/><origin xyz="{xyz}" rpy="0 0 0"/>'
            f'<axis xyz="{axes[k]}"/>{limit}</joint>',
        ]
        parent = f"link{k}"
    return "\n".join(parts + ["</robot>"])
