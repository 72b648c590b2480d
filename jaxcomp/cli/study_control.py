"""`jaxcomp study control`: tracking error and compliance of the impedance controller across
randomized model errors, one MJX world per simulated true robot.

The options and the printout; the study is ``jaxcomp.studies.control`` (imported inside the
command, so that ``jaxcomp --help`` stays quick).
"""

import click

from jaxcomp.cli.model_options import model_options
from jaxcomp.cli.robot_options import gains_option
from jaxcomp.cli.shared_options import choice_option
from jaxcomp.cli.study import run_into, scale_options, study


@study.command("control")
@model_options("gen3_lite", "Robot model studied")
@click.option("--worlds", type=int, default=64, show_default=True, help="Simulated robots.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every draw.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="study_control")
@click.option(
    "--duration",
    type=float,
    default=None,
    help="Seconds of half-circle tracking after the 2 s compliance phase (default: the whole "
    "lead-in and passes, about 25 s for 2 passes). Short runs (e.g. 1) suit the CPU.",
)
@click.option("--passes", type=int, default=2, show_default=True, help="Half-circle passes.")
@click.option("--force", type=float, default=10.0, show_default=True, help="Push, N.")
@gains_option("Impedance gains preset (see `jaxcomp control --help`).")
@choice_option(
    "--controller",
    choices=("identified", "nominal"),
    help="identified: the truth perturbed by --params-error and --com-error; nominal: the "
    "model's nominal ratios, no friction compensation, nominal COM.",
)
@click.option(
    "--params-error",
    type=float,
    default=0.05,
    show_default=True,
    help="Relative ratio and friction errors of the controller, drawn U(-E, E) per joint.",
)
@click.option(
    "--com-error",
    type=float,
    default=0.002,
    show_default=True,
    help="COM errors of the controller, m, drawn U(-D, D) per axis of every moving link.",
)
@click.option("--noise", type=float, default=0.05, show_default=True, help="Current noise, A.")
@choice_option(
    "--push-direction",
    "push",
    choices=("horizontal", "sphere"),
    help="Push directions, uniform in the horizontal plane or on the sphere (pushing down "
    "10 N at the home pose overloads joint 1 with the friction compensation).",
)
@click.option("--devices", type=int, default=None, help="Shard over N devices (default all).")
@scale_options
@click.option("--progress/--no-progress", default=True, show_default=True)
def control(
    model: str,
    joints: str | None,
    site: str | None,
    worlds: int,
    seed: int,
    out_dir: str,
    duration: float | None,
    passes: int,
    force: float,
    preset: str,
    controller: str,
    params_error: float,
    com_error: float,
    noise: float,
    push: str,
    devices: int | None,
    chunk_worlds: int | None,
    resume: bool,
    distributed: bool,
    coordinator: str | None,
    num_processes: int | None,
    process_id: int | None,
    progress: bool,
) -> None:
    """Tracking error and compliance across randomized model errors (MJX, one world each).

    Each world: a true Gen3 Lite (paper ratios x U(0.9, 1.1), friction x U(0.8, 1.2), COM
    offsets U(+-4 mm)) under the impedance controller in CURRENT mode at 1 kHz, with the
    controller's params off by --params-error / --com-error (or nominal). A push of --force N
    in a random (by default horizontal) direction measures the compliance ratio
    displacement / (F / K_d); then the paper's half circle (r 0.315 m, 0.101 m/s) measures
    the tracking error. Writes DIR/study.json and DIR/tracking.png, DIR/compliance.png.
    Nothing is written on error but the finished chunks (DIR/chunks), which --resume keeps.
    The same --seed reproduces the numbers (timings aside; other --chunk-worlds to rounding)
    whatever the processes: each world's draws and noise follow its index.
    """
    from jaxcomp.studies.processes import start_processes

    processes = start_processes(distributed, coordinator, num_processes, process_id)
    from jaxcomp.studies.control import ControlSettings, study_into, summary

    settings = ControlSettings(
        worlds,
        seed,
        duration=duration,
        passes=passes,
        force=force,
        gains=preset,
        params_error=params_error,
        com_error=com_error,
        nominal=controller == "nominal",
        noise=noise,
        push=push,
        devices=devices,
        chunk_worlds=chunk_worlds,
    )
    result = run_into(study_into, settings, out_dir, model=model, joints=joints, site=site,
                      progress=progress, resume=resume, processes=processes)  # fmt: skip
    if result is not None:
        click.echo(summary(result.report, result.paths[0]))
