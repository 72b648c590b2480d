"""`jaxcomp models`: the built-in robot models and the joints jaxcomp drives on each."""

import json

import click

from jaxcomp.cli.group import cli


@cli.command()
@click.option("--json", "as_json", is_flag=True, help="Print a JSON list instead of lines.")
def models(as_json: bool) -> None:
    """List the built-in robot models: current-controlled joints, held joints, source file.

    Held joints (gripper fingers, joints without a current mode) are welded at their held
    position; a mobile model's base joints are counted apart. A model jaxcomp cannot load as
    an arm shows why instead.
    """
    from jaxcomp import builtin_models, load_robot
    from jaxcomp.errors import JaxcompError

    entries = []
    for name in builtin_models():
        try:
            robot = load_robot(name)
        except JaxcompError as exc:
            entries.append({"name": name, "error": str(exc)})
            continue
        controlled = list(getattr(robot, "controlled_joints", robot.joint_names))
        held = {k: float(v) for k, v in getattr(robot, "held_joints", {}).items()}
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
        if "error" in e:
            click.echo(f"{e['name']:<18} not loadable as an arm: {e['error']}")
            continue
        base = f"  {len(e['base'])} base" if e["base"] else ""
        counts = f"{len(e['controlled'])} controlled  {len(e['held'])} held{base}"
        click.echo(f"{e['name']:<18} {counts:<30} {e['source']}")
