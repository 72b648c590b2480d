"""`jaxcomp info`: what a robot model holds."""

import json

import click
import numpy as np

from jaxcomp.cli.group import cli


@cli.command()
@click.argument("robot", default="gen3_lite")
@click.option(
    "--pose",
    default=None,
    help="Named pose for the gravity torques (an MJCF keyframe, or home / preferred / rest / "
    "zero, which every robot has); default: home.",
)
@click.option("--joints", default=None, metavar="NAME,NAME,...", help="Current-controlled joints.")
@click.option("--site", default=None, metavar="NAME", help="End-effector site.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of tables.")
def info(robot: str, pose: str | None, joints: str | None, site: str | None, as_json: bool) -> None:
    """Show a robot's joints, link masses and gravity torques at a pose.

    ROBOT is a built-in name (see `jaxcomp models`) or a path to an MJCF or URDF file.
    """
    from jaxcomp import load_robot
    from jaxcomp.cli.model_options import joint_names

    r = load_robot(robot, joints=joint_names(joints), site=site)
    pose = pose or "home"
    q = r.pose(pose)
    g = np.asarray(r.gravity(q))
    params = r.nominal_params()
    masses = np.asarray(params.mass)
    lo, hi = r.joint_limits.T
    kinds = ["revolute" if h else "prismatic" for h in r.tree.is_hinge]
    if as_json:
        out = {
            "robot": r.name,
            "source": str(r.source),
            "joints": [
                {"name": n, "type": k, "lower": float(a), "upper": float(b), "effort": float(e)}
                for n, k, a, b, e in zip(r.joint_names, kinds, lo, hi, r.effort_limits, strict=True)
            ],
            "links": {n: float(m) for n, m in zip(r.link_names, masses, strict=True)},
            "held_joints": r.held_joints,
            "end_effector": r.end_effector,
            "pose": pose,
            "q": q.tolist(),
            "gravity_torque": g.tolist(),
        }
        click.echo(json.dumps(out, indent=2))
        return
    click.echo(f"{r.name}  ({r.source})")
    w = max(12, *(len(n) + 2 for n in r.joint_names))
    wl = max(16, *(len(n) + 2 for n in r.link_names))
    click.echo(f"\n{r.nv} joints (current-controlled, and a mobile base's)")
    click.echo(f"  {'joint':<{w}}{'type':<11}{'lower':>9}{'upper':>9}  {'effort limit':>12}")
    for n, k, a, b, e in zip(r.joint_names, kinds, lo, hi, r.effort_limits, strict=True):
        if k == "revolute":
            click.echo(
                f"  {n:<{w}}{k:<11}{np.rad2deg(a):>7.1f}°{np.rad2deg(b):>8.1f}°{e:>10.1f} N m"
            )
        else:
            click.echo(f"  {n:<{w}}{k:<11}{a:>7.3f}m{b:>8.3f}m{e:>10.1f} N")
    click.echo(f"\n{len(r.link_names)} links, total mass {masses.sum():.4f} kg")
    for n, m in zip(r.link_names, masses, strict=True):
        click.echo(f"  {n:<{wl}}{m:>9.4f} kg")
    shown = np.where(r.tree.is_hinge, np.rad2deg(q), q)
    click.echo(f"\nGravity torque g(q) at pose '{pose}', q = {np.round(shown, 2)} (deg or m)")
    click.echo("  the torque each joint must apply to hold the arm still, N m (N for slides)")
    for n, t in zip(r.joint_names, g + 0.0, strict=True):
        click.echo(f"  {n:<{w}}{t:>10.4f}")
    held = ", ".join(f"{n} at {v:.4g}" for n, v in r.held_joints.items()) or "none"
    click.echo(f"\nheld joints (welded, rad or m): {held}")
    click.echo(f"end effector: site {r.end_effector!r}")
