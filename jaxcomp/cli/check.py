"""`jaxcomp check`: is a recording or params file usable and plausible, before it is fitted or
drives an arm."""

import click

from jaxcomp.cli.group import cli
from jaxcomp.errors import InputError


@cli.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
def check(files: tuple[str, ...]) -> None:
    """Check recordings (.npz) and params files (.json) without running anything.

    A recording is validated (fields, shapes, units) and checked for what no real arm records:
    currents beyond twice the model's current limit (mA?), a swept joint whose current is
    zero; the recordings together must sweep every joint both ways. A params file is checked
    against its model (the file's `model` and `joints`) for physical plausibility: ratios,
    friction losses against the current limits, COM offsets against the links' sizes (see
    docs/plausibility.md). Prints one line per good file; the first bad one ends in one
    `error:` line, status 2.
    """
    from jaxcomp.plausibility import check_params, check_recordings
    from jaxcomp.recording import load_recording
    from jaxcomp.robot import load_robot
    from jaxcomp.robot_params import RobotParams

    recordings = []
    for path in files:
        if path.endswith(".npz"):
            rec = load_recording(path)
            recordings.append(rec)
            click.echo(f"{path}: recording of {rec.model}, {rec.n_samples} samples")
        elif path.endswith(".json"):
            params = RobotParams.load(path)
            robot = load_robot(params.model, joints=params.joints)
            check_params(params, robot, f"the params in {path}")
            click.echo(f"{path}: params of {params.model} ({params.method}), plausible")
        else:
            raise InputError(f"{path}: expected a recording (.npz) or a params file (.json)")
    if recordings:
        if len({(r.model, r.robot().controlled_joints) for r in recordings}) > 1:
            raise InputError("the recordings are of different models or joints")
        check_recordings(recordings)
        click.echo(f"{len(recordings)} recording(s): every joint swept both ways, plausible")
