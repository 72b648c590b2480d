"""Write a robot's kinematic tree and inertials as URDF, e.g. for pinocchio.

Supported: every body has at most one joint, anchored at the body origin (true of URDF-born
models and of jaxcomp's own). Sites become massless child links, so pinocchio has a frame for
each. Joint reference positions (MuJoCo ``ref``) must be zero.
"""

from xml.sax.saxutils import quoteattr

import numpy as np
from scipy.spatial.transform import Rotation

from jaxcomp.errors import ModelError
from jaxcomp.kinematic_tree import KinematicTree
from jaxcomp.params import InertialParams


def _origin(pos: np.ndarray, rot: np.ndarray) -> str:
    rpy = Rotation.from_matrix(rot).as_euler("xyz")
    xyz = " ".join(f"{v:.17g}" for v in pos)
    return f'<origin xyz="{xyz}" rpy="{" ".join(f"{v:.17g}" for v in rpy)}"/>'


def _inertial(mass: float, com: np.ndarray, inertia: np.ndarray) -> str:
    i = inertia
    values = {"ixx": i[0, 0], "ixy": i[0, 1], "ixz": i[0, 2], "iyy": i[1, 1], "iyz": i[1, 2]}
    values["izz"] = i[2, 2]
    attrs = " ".join(f'{k}="{v:.17g}"' for k, v in values.items())
    return (
        f'<inertial>{_origin(com, np.eye(3))}<mass value="{mass:.17g}"/>'
        f"<inertia {attrs}/></inertial>"
    )


def to_urdf(tree: KinematicTree, params: InertialParams | None = None, name: str = "robot") -> str:
    """URDF text of ``tree`` with inertials ``params`` (default: the model's).

    Args:
        tree: the kinematic tree.
        params: link masses (nb,) kg, COMs (nb, 3) m and inertias (nb, 3, 3) kg m^2 in the
            link frames; default the model's.
        name: the URDF robot's name.

    Returns:
        The URDF document, one element a line.

    Raises:
        ModelError: a joint with a nonzero reference or anchor, or a body with several joints.
    """
    p = tree.nominal if params is None else params
    mass, com, inertia = (np.asarray(x, dtype=float) for x in p)
    if np.any(tree.joint_ref != 0):
        raise ModelError("URDF export needs joint reference positions (ref) of zero")
    if np.any(np.abs(tree.joint_pos) > 1e-12):
        raise ModelError("URDF export needs every joint anchored at its body's origin")
    lines = [f"<robot name={quoteattr(name)}>", '<link name="world"/>']
    for b, body in enumerate(tree.body_names):
        joints = tree.body_joints[b]
        if len(joints) > 1:
            raise ModelError(f"URDF export: body {body!r} has {len(joints)} joints (max 1)")
        lines.append(
            f"<link name={quoteattr(body)}>{_inertial(mass[b], com[b], inertia[b])}</link>"
        )
        parent = "world" if tree.parent[b] < 0 else tree.body_names[tree.parent[b]]
        origin = _origin(tree.pos[b], tree.rot[b])
        if joints:
            j = joints[0]
            kind = "revolute" if tree.is_hinge[j] else "prismatic"
            lo, hi = tree.joint_range[j]
            if not np.isfinite(lo):  # "continuous" would give pinocchio 2 coordinates
                lo, hi = -1e3, 1e3
            axis = " ".join(f"{v:.17g}" for v in tree.joint_axis[j])
            lines.append(
                f'<joint name={quoteattr(tree.joint_names[j])} type="{kind}">'
                f"<parent link={quoteattr(parent)}/><child link={quoteattr(body)}/>{origin}"
                f'<axis xyz="{axis}"/><limit lower="{lo:.17g}" upper="{hi:.17g}" '
                'effort="1000" velocity="100"/></joint>'
            )
        else:
            lines.append(
                f'<joint name={quoteattr(body + "_fixed")} type="fixed">'
                f"<parent link={quoteattr(parent)}/><child link={quoteattr(body)}/>{origin}</joint>"
            )
    for s, site in enumerate(tree.site_names):
        b = tree.site_body[s]
        parent = "world" if b < 0 else tree.body_names[b]
        lines.append(f"<link name={quoteattr(site)}/>")
        lines.append(
            f'<joint name={quoteattr(site + "_site")} type="fixed">'
            f"<parent link={quoteattr(parent)}/><child link={quoteattr(site)}/>"
            f"{_origin(tree.site_pos[s], tree.site_rot[s])}</joint>"
        )
    lines.append("</robot>")
    return "\n".join(lines)
