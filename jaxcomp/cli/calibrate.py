"""`jaxcomp calibrate` and `jaxcomp fit`: record calibration sweeps, fit params files."""

from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np

from jaxcomp import identify
from jaxcomp.cli.console_options import console_options
from jaxcomp.cli.group import cli
from jaxcomp.cli.kortex_backend import open_kortex_arm
from jaxcomp.cli.model_options import joint_names, model_options
from jaxcomp.cli.robot_options import backend_option, ip_option
from jaxcomp.errors import InputError
from jaxcomp.files import check_outputs
from jaxcomp.identify.fitting import METHODS


def _warn(params) -> None:
    """The fit's warnings (confounded or unexcited ratios, and the cure), one line each."""
    from jaxcomp.identify.joint_fit import warnings_of

    for line in warnings_of(params):
        click.echo(line, err=True)


#: What ``jaxcomp calibrate`` writes into its folder (with the recording's part files).
CALIBRATION_FILES = (
    "recording.npz",
    "recording.npz.parts",
    "params.json",
    "params_scipy.json",
    "sweeps.png",
    "truth.json",
)


def _table(columns: dict, links: list[str]) -> str:
    """Parameters side by side: one column per params set."""
    names = list(columns)
    n = len(next(iter(columns.values())).ratio)
    head = f"{'':<26}" + "".join(f"{k:>12}" for k in names)
    rows = [head, "-" * len(head)]

    def row(label, values):
        rows.append(f"{label:<26}" + "".join(f"{v:>12.4f}" for v in values))

    for j in range(n):
        row(f"ratio[{j}] A/(N m)", [p.ratio[j] for p in columns.values()])
    for j in range(n):
        row(f"friction[{j}] A", [p.friction[j] for p in columns.values()])
    for j in range(n):
        row(
            f"phase_shift[{j}] deg",
            [
                np.rad2deg(p.phase_shift[j]) if p.phase_shift is not None else np.nan
                for p in columns.values()
            ],
        )
    for link in links:
        for k, ax in enumerate("xyz"):
            row(
                f"com {link}.{ax} mm",
                [1e3 * p.com_offset.get(link, np.zeros(3))[k] for p in columns.values()],
            )
    return "\n".join(rows)


@cli.command()
@backend_option(
    "sim: the simulated --model with a hidden true robot (written to DIR/truth.json); kortex: "
    "the real Gen3 Lite through kortex_api."
)
@model_options("gen3_lite", "Robot model (the nominal model the fit starts from)")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    default="calibration",
    show_default=True,
    help="Output folder: recording.npz, params.json (joint JAX fit), params_scipy.json (the "
    "paper's per-joint fit), sweeps.png, truth.json (sim).",
)
@click.option(
    "--plan",
    default="default",
    show_default=True,
    help="default: the paper's sweeps (up to -100..100 deg inside each joint's limits at "
    "40 deg/s, several held poses per joint); short: one -40..40 deg sweep per joint (a quick "
    "check); or a plan JSON file.",
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Seed of the simulator's true robot and noise (sim only).",
)
@click.option(
    "--truth",
    "truth_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="True robot for the simulator, a params JSON (sim only; default: drawn "
    "from --seed around the model's nominal figures; the Gen3 Lite: the paper's ratios and "
    "frictions; COM offsets of a few mm).",
)
@ip_option
@click.option(
    "--resume",
    is_flag=True,
    help="Continue an interrupted calibration in DIR (keeps its finished sweeps); refused when "
    "the plan, model, joints, --robot, --seed or --truth differ from the interrupted run's.",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Discard the calibration DIR holds and record a new one (without it, a DIR that holds "
    "one is refused).",
)
@click.option("--viewer", is_flag=True, help="Show the MuJoCo viewer (sim, needs a display).")
@console_options(
    "the calibration: the arm sweeping, its currents, the progress; stop from the page"
)
def calibrate(
    backend,
    model,
    joints,
    site,
    out_dir,
    plan,
    seed,
    truth_file,
    ip,
    resume,
    overwrite,
    viewer,
    console,
    port,
    host,
    on_disconnect,
) -> None:
    """Run the calibration sweeps, record them at 1 kHz, and fit with both methods.

    Each current-controlled joint is swept (up to -100..+100 deg, inside its limits) and back
    at constant speed with the robot's own position servo while the others are held, as in the
    paper (Section IV-A). The recording is written incrementally: an interrupted run (Ctrl-C,
    a fault) leaves DIR/recording.npz with its finished sweeps, and --resume records the
    others. Then the joint JAX fit and the paper's scipy fit run on it and their parameters
    are printed side by side (with the truth, on the simulator). One run at a time writes
    into DIR (a lock file).
    """
    from jaxcomp.files import output_folder
    from jaxcomp.identify.named_plans import PLANS, check_plan_name, named_plan, random_count
    from jaxcomp.identify.plots import plot_sweeps
    from jaxcomp.identify.recorder import record
    from jaxcomp.robot import load_robot

    if resume and overwrite:
        raise InputError(
            "--resume continues the calibration in --out, --overwrite discards it: give one of them"
        )
    check_plan_name(plan)
    plan_file = plan if plan not in PLANS and random_count(plan) is None else None
    check_outputs(  # truth.json: a --truth given there is written back unchanged
        tuple(p for p in (truth_file, plan_file) if p),
        [("--out", str(Path(out_dir) / f)) for f in CALIBRATION_FILES if f != "truth.json"],
    )
    robot = load_robot(model, joints=joint_names(joints), site=site)
    if backend == "kortex" and robot.name != "gen3_lite":
        raise InputError(f"--robot kortex drives a Gen3 Lite; --model {model} is not one")
    the_plan = named_plan(robot, plan)
    click.echo(f"plan: {len(the_plan.sweeps)} sweeps, about {the_plan.duration():.0f} s of motion")
    truth = None
    settings: dict = {"robot": backend}
    if backend == "sim":
        from jaxcomp.hardware import TrueRobot

        truth = TrueRobot.load(truth_file, robot) if truth_file else TrueRobot.draw(robot, seed)
        settings |= {"seed": seed, "truth": truth.to_dict()}
    with output_folder(out_dir) as out:
        _prepare_folder(out, the_plan, robot, settings, resume, overwrite)
        if truth is not None:
            from jaxcomp.hardware import Simulator

            _save(truth, out / "truth.json")
            sim = Simulator(robot, truth, seed=seed, viewer=viewer)
            arm = sim.arm
        else:
            arm = open_kortex_arm(ip, robot=robot)
        page = _CalibrationPage(arm, robot, port, host, on_disconnect) if console else None
        try:
            with arm:
                rec = record(
                    arm,
                    the_plan,
                    out / "recording.npz",
                    model=robot,
                    resume=resume,
                    settings=settings,
                    on_state=page.on_state if page is not None else None,
                )
        except KeyboardInterrupt:
            kept = out / "recording.npz"
            click.echo(
                f"interrupted: the finished sweeps are in {kept}; --resume records the others"
                if kept.is_file()
                else "interrupted before the first sweep ended: nothing kept",
                err=True,
            )
            raise
        finally:
            if page is not None:
                page.close()
        click.echo(f"recorded {rec.n_samples} samples -> {out / 'recording.npz'}")
        fits = {}
        for method in METHODS:
            fits[method] = identify.fit([rec], method)
            click.echo(f"{method} fit: {fits[method].fit_seconds:.3f} s")
        click.echo("(the first JAX fit on a machine includes its XLA compilation; it is cached)")
        _save(fits["jax"], out / "params.json")
        _save(fits["scipy"], out / "params_scipy.json")
        columns = dict(fits)
        if truth is not None:
            columns["truth"] = truth.params
        links = sorted({k for p in columns.values() for k in p.com_offset}, key=robot.link_index)
        click.echo(_table(columns, links))
        _warn(fits["jax"])
        plot_sweeps(rec, columns, out / "sweeps.png")
    click.echo(f"wrote {out / 'params.json'}, {out / 'params_scipy.json'}, {out / 'sweeps.png'}")


class _CalibrationPage:
    """The browser console of a ``jaxcomp calibrate`` run: frames and progress from
    ``record``'s ``on_state``; the page's stop interrupts the calibration as Ctrl-C does
    (the finished sweeps are kept for --resume)."""

    def __init__(self, arm, robot, port: int, host: str, on_disconnect: str):
        import threading

        from jaxcomp.console.link import ConsoleLink

        self.stop = threading.Event()
        self.link = ConsoleLink(
            robot,
            tuple(arm.joint_names),
            handler=self.handle,
            port=port,
            host=host,
            title=f"jaxcomp calibrate: {robot.name}",
            controls="calibrate",
            on_lost=on_disconnect,
            on_stop=self.stop.set,
        )
        self.done = 0.0
        click.echo(f"console: {self.link.url}", err=True)
        self.link.status(state="calibrating", detail="jaxcomp calibrate", arm_modes="position")

    def handle(self, name: str, args: dict) -> str:
        if name == "stop":
            self.stop.set()
            return "stopping the calibration (the finished sweeps are kept: --resume)"
        raise InputError(f"{name}: not while the console is attached to `jaxcomp calibrate`")

    def on_state(self, state, done: float) -> None:
        if self.stop.is_set():
            raise KeyboardInterrupt
        if self.link.feed.state("calibrating", state) and done - self.done >= 0.01:
            self.done = done
            self.link.status(progress=done)

    def close(self) -> None:
        self.link.status(state="ended", detail="the calibration is over", progress=self.done)
        self.link.close()


def _save(params, path: Path) -> None:
    """``params.save(path)`` (atomic); FileError naming ``path`` when it cannot be written."""
    from jaxcomp.files import writing

    with writing(path):
        params.save(path)


def _prepare_folder(out: Path, plan, robot, settings: dict, resume: bool, overwrite: bool):
    """Check what the calibration folder ``out`` holds against what was asked (InputError):
    --resume needs an interrupted calibration of the same plan, model and ``settings`` (or
    none); otherwise an earlier calibration is refused, or removed with --overwrite."""
    import shutil

    from jaxcomp.files import existing, writing
    from jaxcomp.identify.recorder import check_resume

    recording = out / "recording.npz"
    held = existing(out, CALIBRATION_FILES)
    if resume:
        done = check_resume(recording, plan, robot, settings)
        if (out / CALIBRATION_FILES[1]).exists():
            click.echo(f"resuming: {len(done)} of {len(plan.sweeps)} sweeps already recorded")
        elif recording.exists():
            raise InputError(
                f"--resume: {recording} is complete, there is nothing to resume; fit it with "
                "`jaxcomp fit`, or record a new calibration with --overwrite"
            )
        return
    if held and not overwrite:
        raise InputError(
            f"--out {out} holds an earlier calibration ({', '.join(held)}): --resume continues "
            "it, --overwrite replaces it, or choose another --out"
        )
    for name in held:
        with writing(out / name, "cannot remove"):
            if (out / name).is_dir():
                shutil.rmtree(out / name)
            else:
                (out / name).unlink()


@cli.command()
@click.argument("recordings", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option(
    "--method",
    type=click.Choice(METHODS),
    default="jax",
    show_default=True,
    help="jax: all joints and recordings jointly (gradient-based, with standard "
    "errors); scipy: the paper's per-joint fit (one recording).",
)
@click.option(
    "--each",
    is_flag=True,
    help="Fit every recording on its own (vmapped batch); writes a JSON list.",
)
@click.option(
    "--out",
    "out_file",
    type=click.Path(dir_okay=False),
    required=True,
    help="Params JSON to write (a list with --each).",
)
@click.option(
    "--plot",
    "plot_file",
    type=click.Path(dir_okay=False),
    default=None,
    help="PNG: sweeps and model (one fit) or boxplots normalized by the median (--each).",
)
@click.option(
    "--com-prior",
    type=click.FloatRange(min=0.0, min_open=True),
    default=None,
    help="Prior standard deviation of every link's COM offset per axis, m (default: the "
    "model's jaxcomp_com_prior, else 10 % of each link's radius of gyration, >= 2 mm).",
)
@click.option(
    "--transfers/--no-transfers",
    default=True,
    show_default=True,
    help="JAX fit: also use the moves between sweeps (their constant-velocity cruise, every "
    "joint at once, Coriolis torque modelled); --no-transfers fits the sweeps alone, e.g. "
    "when the arm's own trajectory generator made the moves.",
)
def fit(recordings, method, each, out_file, plot_file, com_prior, transfers) -> None:
    """Fit ratio, friction and COM offsets to calibration recordings (.npz).

    Several recordings of one robot are fitted jointly into one params set (e.g. two mountings
    with different gravity, or with and without a known payload), unless --each is given.
    Nothing is written when a recording is invalid or a fit does not converge.
    """
    from contextlib import ExitStack

    from jaxcomp.files import output_folder

    check_outputs(recordings, [("--out", out_file), ("--plot", plot_file)])
    with ExitStack() as stack:
        folders = {Path(p).absolute().parent for p in (out_file, plot_file) if p}
        for folder in sorted(folders):
            stack.enter_context(output_folder(folder, "the folder of --out"))
        _fit_into(recordings, method, each, out_file, plot_file, com_prior, transfers)


def _fit_into(recordings, method, each, out_file, plot_file, com_prior, transfers) -> None:
    """``jaxcomp fit`` once its output folders are locked."""
    from jaxcomp.files import writing
    from jaxcomp.recording import load_recording, load_recordings
    from jaxcomp.robot_params import write_json_atomic

    start = time.perf_counter()
    if each:
        results = identify.fit_each(  # read as the fits go
            load_recordings(recordings),
            method,
            com_prior=com_prior,
            transfers=transfers,
            progress=True,
        )
        with writing(out_file):
            write_json_atomic(out_file, [p.to_dict() for p in results])
        click.echo(
            f"{len(results)} fits ({method}) in {time.perf_counter() - start:.2f} s -> {out_file}"
        )
        if plot_file:
            from jaxcomp.identify.plots import plot_batch

            plot_batch(results, plot_file)
        return
    recs = [load_recording(p) for p in recordings]
    params = identify.fit(recs, method, com_prior=com_prior, transfers=transfers)
    _save(params, Path(out_file))
    robot = recs[0].robot()
    links = sorted(params.com_offset, key=robot.link_index)
    click.echo(_table({method: params}, links))
    if method == "jax":
        _warn(params)
    click.echo(f"fit in {params.fit_seconds:.3f} s -> {out_file}")
    if plot_file:
        from jaxcomp.identify.plots import plot_sweeps

        plot_sweeps(recs[0], {method: params}, plot_file)
