"""`jaxcomp models`: the built-in robot models and the joints jaxcomp drives on each."""

import json

import click

from jaxcomp.cli.group import cli


@cli.command()
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list instead of lines.")
def models(as_json: bool) -> None:
    """List the built-in robot models: current-controlled joints, held joints, source file.

    Held joints (gripper fingers, joints without a current mode) are welded at their held
    position; a mobile model's base joints are counted apart.
    """
    from jaxcomp import builtin_models, load_robot

    entries = []
    for name in builtin_models():
        robot = load_robot(name)
        controlled = list(robot.controlled_joints)
        held = {k: float(v) for k, v in robot.held_joints.items()}
        entries.append(
            {
                "name": name,
                "controlled": controlled,
                "held": held,
                "base": [n for n in robot.joint_names if n not in controlled],
                "source": str(robot.source),
            }
        )
    if as_json:
        click.echo(json.dumps(entries, indent=2))
        return
    for e in entries:
        base = f"  {len(e['base'])} base" if e["base"] else ""
        counts = f"{len(e['controlled'])} controlled  {len(e['held'])} held{base}"
        click.echo(f"{e['name']:<18} {counts:<30} {e['source']}")
