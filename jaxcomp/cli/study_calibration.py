"""`jaxcomp study calibration`: how well calibration finds thousands of simulated true robots.

The options and the printout; the study is ``jaxcomp.studies.calibration`` (imported inside the
command, so that ``jaxcomp --help`` stays quick), its one call ``calibration_outputs.study_into``.
"""

import click

from jaxcomp.cli.model_options import model_options
from jaxcomp.cli.shared_options import com_prior_option
from jaxcomp.cli.study import run_into, scale_options, study


@study.command("calibration")
@model_options("gen3_lite", "Robot model studied")
@click.option("--worlds", type=int, required=True, help="Simulated true robots N (>= 1).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every draw.")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(),
    default="study_calibration",
    show_default=True,
    help="Report folder: study.json, worlds.npz, errors.png, coverage.png.",
)
@click.option("--devices", type=int, default=None, help="Shard over K devices (default all).")
@click.option(
    "--baseline-sample",
    type=int,
    default=16,
    show_default=True,
    help="Also fit M worlds with the paper's scipy fit (0: none): the first worlds of each "
    "plan, M spread over the plans.",
)
@click.option(
    "--plan",
    default="default",
    show_default=True,
    help="default: the paper's plan (~230 s of sweeps); short: one +-40 deg sweep per joint "
    "(~30 s, for CPU runs and CI); random: a plan drawn from --seed (at least half the joints "
    "in random order, each from a random held pose within the middle 80 % of the ranges, over "
    "a random 90-200 deg span at a random 10-40 deg/s, drawn again where the model overloads "
    "an actuator, reaches the floor or touches itself); random:K: K such plans, the worlds cut "
    "into K contiguous groups, one plan each; or a plan JSON file.",
)
@click.option(
    "--every",
    type=int,
    default=10,
    show_default=True,
    help="Record every k-th 1 kHz state (10: 100 Hz) for the fits.",
)
@click.option(
    "--com-offset",
    type=float,
    default=0.004,
    show_default=True,
    help="True COM offsets U(-c, c) m per axis of every moving link.",
)
@click.option(
    "--model-error",
    type=(float, float),
    default=(0.2, 0.3),
    show_default=True,
    help="True ratios (per actuator type) off nominal, friction torques off the paper's, "
    "by 1 +- U(LO, HI) (friction: - where + would take over 35 % of the effort limit).",
)
@click.option(
    "--noise",
    type=float,
    default=None,
    help="True current noise (std), A (default: the model's; 0.05 A on the Gen3 Lite).",
)
@click.option(
    "--viscous",
    type=float,
    default=0.0,
    show_default=True,
    help="True viscous friction U(0, v) N m s/rad per joint.",
)
@com_prior_option(
    "The JAX fit's prior standard deviation of every link's COM offset per axis, m "
    "(default: the spread the truths are drawn from, --com-offset / sqrt(3); jaxcomp fit's "
    "default is the model's, 10 % of each link's radius of gyration)."
)
@click.option(
    "--poses", type=int, default=1000, show_default=True, help="Poses of the gravity error."
)
@click.option(
    "--world-batch",
    type=int,
    default=None,
    help="Worlds per MJX run (default: all on an accelerator, one per device on the CPU).",
)
@click.option("--fit-batch", type=int, default=None, help="Fits per vmapped batch (default all).")
@click.option(
    "--parallel-sweeps/--sequential-sweeps",
    "parallel",
    default=None,
    help="Simulate the plan's sweeps side by side (K worlds per robot, each from rest where "
    "the sweep before it ends) or in turn. Default: side by side on an accelerator.",
)
@click.option(
    "--keep-samples",
    type=int,
    default=0,
    show_default=True,
    help="Save the recorded samples of the first N worlds as recordings, "
    "DIR/samples/world_00000.npz, ... (for plots; jaxcomp fit reads them).",
)
@scale_options
@click.option("--progress/--no-progress", default=True, show_default=True)
def calibration(
    model: str,
    joints: str | None,
    site: str | None,
    worlds: int,
    seed: int,
    out_dir: str,
    devices: int | None,
    baseline_sample: int,
    plan: str,
    every: int,
    noise: float | None,
    com_offset: float,
    model_error: tuple[float, float],
    viscous: float,
    com_prior: float | None,
    poses: int,
    world_batch: int | None,
    fit_batch: int | None,
    progress: bool,
    parallel: bool | None,
    chunk_worlds: int | None,
    resume: bool,
    keep_samples: int,
    distributed: bool,
    coordinator: str | None,
    num_processes: int | None,
    process_id: int | None,
) -> None:
    """Calibrate N simulated true robots at once and compare with their truth (MJX).

    Each world: a --model arm whose ratios and friction losses are off nominal by 20-30 % and
    whose links' COM are off by a few mm, with current noise. The calibration plan is recorded
    in all worlds at once on MJX (1 kHz, recorded at 1 kHz / --every), every world is fitted
    with the joint JAX fit (batched on the accelerator) and M of them (spread over the plans)
    with the paper's scipy fit. DIR/study.json: per-parameter errors against the truth,
    gravity-current error at random poses (and how often the JAX fit's, pooled over the swept
    joints, is worse than the scipy fit's), the largest error of an identified ratio, coverage of
    the reported standard errors, Cramer-Rao comparison, run times;
    DIR/errors.png, DIR/coverage.png; DIR/worlds.npz: per-world truth and estimates. Nothing
    is written on error but the finished chunks (DIR/chunks), which --resume keeps. The same
    --seed reproduces the numbers (timings aside), whatever --chunk-worlds and the processes.
    """
    from jaxcomp.studies.processes import start_processes

    processes = start_processes(distributed, coordinator, num_processes, process_id)
    from jaxcomp.studies.calibration_outputs import study_into, summary
    from jaxcomp.studies.calibration_settings import CalibrationSettings
    from jaxcomp.studies.truth_draw import TruthSpread

    settings = CalibrationSettings(
        worlds,
        seed,
        plan=plan,
        every=every,
        spread=TruthSpread(model_error, com_offset=com_offset, noise=noise, viscous=viscous),
        baseline_sample=baseline_sample,
        devices=devices,
        world_batch=world_batch,
        fit_batch=fit_batch,
        poses=poses,
        parallel=parallel,
        com_prior=com_prior,
        chunk_worlds=chunk_worlds,
        keep_samples=keep_samples,
    )
    result = run_into(study_into, settings, out_dir, model=model, joints=joints, site=site,
                      progress=progress, resume=resume, processes=processes)  # fmt: skip
    if result is not None:
        click.echo(summary(result.report))
        click.echo("wrote " + ", ".join(str(p) for p in result.paths))
