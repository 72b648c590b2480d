"""Test robots written by the tests themselves, as URDF text (random but seeded)."""

import numpy as np
from scipy.spatial.transform import Rotation


def _inertia(rng: np.random.Generator) -> np.ndarray:
    """A physically valid inertia tensor (triangle inequality holds) in a random frame."""
    a, b = rng.uniform(0.002, 0.02, 2)
    c = rng.uniform(abs(a - b) + 1e-4, a + b - 1e-4)
    rot = Rotation.random(random_state=rng).as_matrix()
    return rot @ np.diag([a, b, c]) @ rot.T


def _link(name: str, rng: np.random.Generator) -> str:
    i = _inertia(rng)
    com = rng.uniform(-0.08, 0.08, 3)
    mass = rng.uniform(0.3, 2.0)
    return (
        f'<link name="{name}"><inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>'
        f'<mass value="{mass}"/><inertia ixx="{i[0, 0]}" ixy="{i[0, 1]}" ixz="{i[0, 2]}" '
        f'iyy="{i[1, 1]}" iyz="{i[1, 2]}" izz="{i[2, 2]}"/></inertial></link>'
    )


def _joint(name, kind, parent, child, rng, axis=None) -> str:
    xyz = rng.uniform(-0.15, 0.15, 3) + np.array([0, 0, 0.1])
    rpy = rng.uniform(-np.pi, np.pi, 3)
    axis = rng.normal(size=3) if axis is None else np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    lim = (-0.5, 0.5) if kind == "prismatic" else (-3.0, 3.0)
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="{rpy[0]} {rpy[1]} {rpy[2]}"/>'
        f'<axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>'
        f'<limit lower="{lim[0]}" upper="{lim[1]}" effort="100" velocity="10"/></joint>'
    )


def offset_arm_7dof(seed: int = 7) -> str:
    """A serial 7-joint arm whose joint axes are offset and tilted at random."""
    rng = np.random.default_rng(seed)
    parts = ['<robot name="offset7">', _link("base", rng)]
    for k in range(7):
        parts += [
            _link(f"link{k + 1}", rng),
            _joint(f"j{k + 1}", "revolute", f"link{k}" if k else "base", f"link{k + 1}", rng),
        ]
    return "\n".join(parts + ["</robot>"])


def branched_prismatic(seed: int = 3) -> str:
    """A tree: a prismatic lift on a base, then two revolute branches (one with a slide)."""
    rng = np.random.default_rng(seed)
    links = ["base", "lift", "l1", "l2", "l3", "r1", "r2"]
    parts = ['<robot name="branched">'] + [_link(n, rng) for n in links]
    parts += [
        _joint("lift", "prismatic", "base", "lift", rng, axis=(0, 0, 1)),
        _joint("l1", "revolute", "lift", "l1", rng),
        _joint("l2", "prismatic", "l1", "l2", rng),
        _joint("l3", "revolute", "l2", "l3", rng),
        _joint("r1", "revolute", "lift", "r1", rng),
        _joint("r2", "revolute", "r1", "r2", rng),
    ]
    return "\n".join(parts + ["</robot>"])
