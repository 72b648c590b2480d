"""``jaxcomp console``: the robot driven from the page, one job at a time.

``Operator`` owns the robot (the simulator, or the Gen3 Lite and its base) and the compiled
controller. Its ``run`` loop (the control thread: the caller's, under real-time priority when
granted) holds the arm in position mode at 1 kHz while nothing else runs, and runs what the
page asks:

- a control run (``control.loop.run_control``, real time, until stopped): guidance or
  tracking along a trajectory, with live gains (stiffness, damping, friction compensation:
  changed at once, no recompiling);
- a calibration (``identify.recorder.record``, the plan's sweeps, with its progress), then the
  joint fit (``jaxcomp calibrate``'s, refused when implausible); the fitted params replace the
  controller's (recompiled);
- stop (a run or a calibration ends safely: arm in position mode, base stopped) and clear
  faults.

``handle`` validates each command with the command line's own checks (``parse_trajectory``,
``presets.check_live_gains``, ``named_plan``) on the link's thread and raises their
``InputError`` at once; the job itself runs on the control thread. Runs and calibrations go
into numbered folders under ``out`` (``run-001/recording.npz``, ``calibration-001/...``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from pathlib import Path

import numpy as np

from jaxcomp.errors import InputError, JaxcompError

log = logging.getLogger(__name__)

MODES = ("guidance", "tracking")
#: s: a console run lasts until stopped (or its trajectory ends), at most this.
RUN_LIMIT = 3600.0


def next_folder(out: Path, prefix: str) -> Path:
    """``out/<prefix>-NNN``, the first number not taken.

    Args:
        out: the parent folder.
        prefix: the folders' name, e.g. "run".

    Returns:
        The folder's path (not created).
    """
    k = 1
    while (out / f"{prefix}-{k:03d}").exists():
        k += 1
    return out / f"{prefix}-{k:03d}"


class Operator:
    """Drives one robot for the console (see the module doc).

    Args:
        arm, base: the hardware (``base`` None: an arm alone); sim: the ``Simulator`` behind
            them, or None (real robot: calibration runs in real time).
        robot: the whole model (``Simulator.robot``; the mobile model with a base).
        controller: the compiled ``ImpedanceController`` (arm-alone model).
        preset: its gains preset name; out: folder for runs and calibrations.
        realtime: pace control runs and the hold on the wall clock (1 kHz).
    """

    def __init__(self, arm, base, sim, robot, controller, preset: str, out: Path, realtime=True):
        from jaxcomp.control.impedance_io import live_gains
        from jaxcomp.control.mount import ArmMount, arm_model
        from jaxcomp.control.presets import gain_limits
        from jaxcomp.control.run_link import Tuning

        self.arm, self.base, self.sim, self.robot = arm, base, sim, robot
        self.controller, self.preset, self.out = controller, preset, Path(out)
        self.realtime = realtime
        self.arm_robot = arm_model(robot)
        self.mount = ArmMount.from_model(robot) if base is not None else ArmMount()
        gains = controller.gains
        self.gains = {
            "stiffness": float(gains.stiffness[0]),
            "damping": float(gains.damping[0]),
            "friction": True,
        }
        self.limits = gain_limits(self.arm_robot)._asdict()
        self.tuning = Tuning(live_gains(gains.stiffness, gains.damping, True))
        self.link = None  # the ConsoleLink, once attached
        self.jobs: queue.Queue = queue.Queue()
        self.actions: queue.Queue = queue.Queue()  # quick things for the control thread
        self.stop = threading.Event()  # the active job's stop
        self.closing = threading.Event()
        self.job: str | None = None  # "run", "calibration" while one is active
        self.params_name = "nominal" if controller.params.method == "nominal" else "given"
        self.last_result = None  # the last run's RunResult
        self.last_error: str | None = None  # the last job's error, as the page shows it
        self.fitting = False

    def serve(
        self,
        port: int = 8080,
        host: str = "127.0.0.1",
        title: str = "",
        on_lost: str = "continue",
    ):
        """Start this operator's page (a ``link.ConsoleLink`` wired to ``handle``; the page
        going away with ``on_lost`` "stop" stops the active job) and return it.

        Args:
            port: the page's TCP port (busy: the next free one).
            host: the address it is served on.
            title: the page's title line ("": the robot's name).
            on_lost: "continue" or "stop" (``link.ON_LOST``).

        Returns:
            The ``ConsoleLink`` (its ``url`` the page's).

        Raises:
            InputError: a bad ``port`` or ``on_lost``, or the page's server did not start.
        """
        from jaxcomp.console.link import ConsoleLink
        from jaxcomp.robot_params import BASE_JOINTS

        self.link = ConsoleLink(
            self.robot,
            tuple(self.arm.joint_names),
            tuple(BASE_JOINTS) if self.base is not None else (),
            handler=self.handle,
            port=port,
            host=host,
            title=title or self.robot.name,
            controls="console",
            gains=self.gains,
            limits=self.limits,
            on_lost=on_lost,
            on_stop=self.stop.set,
        )
        return self.link

    # ----------------------------------------------------------------- commands (link thread)
    def handle(self, name: str, args: dict) -> str | None:
        """Run the page's command ``name`` with ``args`` (validated here, the CLI's way);
        InputError for a bad one.

        Args:
            name: "start", "gains", "stop", "clear_faults" or "calibrate".
            args: the command's fields: "start": mode ("guidance", "tracking"), trajectory
                (text, default "static"), stiffness N/m, damping N s/m, friction (bool,
                compensation on); "gains": stiffness, damping, friction; "calibrate": plan
                ("short", "default").

        Returns:
            A line for the page saying what was done.

        Raises:
            InputError: an unknown command, bad arguments, or one refused now (a
                calibration or a fit active).
        """
        if name == "start":
            return self._start(args)
        if name == "gains":
            live = self._live(args)
            self.tuning.set(live)
            return self._describe(live) + (" (now)" if self.job == "run" else " (next run)")
        if name == "stop":
            self.stop.set()
            self.actions.put("stop")
            return "stopping: arm in position mode, base stopped"
        if name == "clear_faults":
            self.actions.put("clear_faults")
            return "clearing the faults"
        if name == "calibrate":
            return self._calibrate(args)
        raise InputError(f"unknown command {name!r}")

    def _live(self, args: dict) -> np.ndarray:
        from jaxcomp.control.impedance_io import live_gains
        from jaxcomp.control.presets import check_live_gains

        k, d = check_live_gains(self.arm_robot, args.get("stiffness"), args.get("damping"))
        friction = args.get("friction", True)
        if not isinstance(friction, bool):
            raise InputError(f"friction compensation must be on or off, got {friction!r}")
        self.gains = {"stiffness": k, "damping": d, "friction": friction}
        return live_gains(k, d, friction)

    @staticmethod
    def _describe(live) -> str:
        return (
            f"stiffness {live[0]:g} N/m, damping {live[3]:g} N s/m, friction compensation "
            f"{'on' if live[6] else 'off'}"
        )

    def _start(self, args: dict) -> str:
        from jaxcomp.control.trajectory import parse_trajectory

        mode = args.get("mode")
        if mode not in MODES:
            raise InputError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        spec = parse_trajectory(str(args.get("trajectory") or "static"))
        live = self._live(args)
        if self.job == "calibration" or self.fitting:
            raise InputError("a calibration is running: stop it first, or wait for its fit")
        if self.job == "run":
            self.stop.set()  # the new run follows once this one has stopped
        self.tuning.set(live)
        self.jobs.put(("run", mode, spec, str(args.get("trajectory") or "static")))
        return f"{mode} mode, {args.get('trajectory') or 'static'}; {self._describe(live)}"

    def _calibrate(self, args: dict) -> str:
        from jaxcomp.identify.named_plans import check_plan_name

        plan_name = str(args.get("plan") or "short")
        check_plan_name(plan_name)
        if plan_name not in ("short", "default"):
            raise InputError("the console calibrates with a named plan: short or default")
        if self.job is not None or self.fitting:
            raise InputError(f"a {self.job or 'fit'} is active: stop it first")
        # the plan is designed on the model (seconds) off the control thread, then queued
        threading.Thread(target=self._plan, args=(plan_name,), daemon=True).start()
        return f"designing the {plan_name} plan, then calibrating"

    def _plan(self, plan_name: str) -> None:
        from jaxcomp.identify.named_plans import named_plan

        try:
            plan = named_plan(self.robot, plan_name)
        except JaxcompError as exc:
            self.status(error=str(exc))
            return
        self.jobs.put(("calibration", plan_name, plan))

    # ----------------------------------------------------------------- the control thread
    def status(self, **fields) -> None:
        """Show ``fields`` on the page, when one is attached (``link.ConsoleLink.status``).

        Args:
            **fields: the status fields, by name, JSON-able.
        """
        if self.link is not None:
            self.link.status(**fields)

    def _arm_status(self, state: str, detail: str = "", modes: str = "", **extra) -> None:
        """The page's status: ``state``, ``detail``, the arm's modes (``modes``: as they will
        be, else as they are), faults, params, gains, and ``extra`` fields."""
        params = self.controller.params
        self.status(
            state=state,
            detail=detail,
            arm_modes=modes or "/".join(sorted({m.value for m in self.arm.modes})),
            base_stopped=self.base is not None and state in ("holding", "stopped"),
            faults=list(self.arm.read().faults),
            ratio=[float(x) for x in params.ratio],
            friction=[float(x) for x in params.friction],
            params=self.params_name,
            gains=self.gains,
            **extra,
        )

    def run(self) -> None:
        """The control thread's loop: hold, or run the next job, until ``close`` or Ctrl-C
        (the arm then holds in position mode)."""
        try:
            self._jobs()
        except KeyboardInterrupt:
            self.closing.set()

    def _jobs(self) -> None:
        while not self.closing.is_set():
            try:
                job = self.jobs.get_nowait()
            except queue.Empty:
                self._hold()
                continue
            self.stop.clear()
            try:
                if job[0] == "run":
                    self._run(*job[1:])
                else:
                    self._calibration(*job[1:])
            except JaxcompError as exc:
                self.last_error = str(exc)
                self.status(error=self.last_error)
            finally:
                self.job = None

    def close(self) -> None:
        """End ``run`` (from any thread) after the active job stops safely."""
        self.closing.set()
        self.stop.set()

    def _base_pose(self):
        return self.base.odometry().pose if self.base is not None else None

    def _hold(self) -> None:
        """Position mode at 1 kHz (paced), frames to the page, until a job or ``close``."""
        from jaxcomp.constants import CONTROL_PERIOD
        from jaxcomp.hardware import HardwareFault

        arm, feed = self.arm, self.link.feed if self.link is not None else None
        if self.base is not None:
            self.base.stop()
        self._arm_status("holding", "position mode")
        period = int(CONTROL_PERIOD * 1e9)
        deadline = time.perf_counter_ns()
        faults = arm.read().faults
        while self.jobs.empty() and not self.closing.is_set():
            self._actions()
            try:
                state = arm.cycle()
            except HardwareFault as exc:
                self._arm_status("holding", "position mode", error=str(exc))
                state = arm.read()
            if state.faults != faults:
                faults = state.faults
                self._arm_status("holding", "position mode")
            if feed is not None:
                feed.state("idle", state, self._base_pose())
            deadline += period
            if self.realtime:  # a holding arm needs no spin-accurate ticks: sleep only
                time.sleep(max(deadline - time.perf_counter_ns(), 0) * 1e-9)
            deadline = max(deadline, time.perf_counter_ns() - 10 * period)

    def _settle(self, seconds: float = 2.0) -> None:
        """Hold the arm until it is still enough to switch modes (at most ``seconds``)."""
        from jaxcomp.constants import CONTROL_PERIOD
        from jaxcomp.control.timing import wait_until

        arm = self.arm
        period = int(CONTROL_PERIOD * 1e9)
        deadline = time.perf_counter_ns()
        for _ in range(int(seconds / CONTROL_PERIOD)):
            state = arm.cycle()
            if np.all(np.abs(state.dq) < 0.5 * arm.limits.switch_speed):
                return
            deadline += period
            if self.realtime:
                wait_until(deadline)

    def _actions(self) -> None:
        while True:
            try:
                action = self.actions.get_nowait()
            except queue.Empty:
                return
            if action == "clear_faults":
                self.arm.clear_faults()
                self._arm_status("holding", "faults cleared")
            elif action == "stop" and self.base is not None:
                self.base.stop()

    def _run(self, mode: str, spec, text: str) -> None:
        from jaxcomp.control.loop import STALL_LIMIT, run_control
        from jaxcomp.control.run_link import RunLink

        self.job = "run"
        out = next_folder(self.out, "run")
        link = RunLink(stop=self.stop, tuning=self.tuning)
        if self.link is not None:
            link.monitor = self.link.feed
        self._settle()
        self._arm_status("running", f"{mode} mode, {text}", modes="current (impedance)")
        result = run_control(
            self.arm,
            self.base,
            self.controller,
            mode,
            spec,
            None,
            out,
            self.realtime,
            mount=self.mount,
            model=self.robot.reference,
            default_duration=RUN_LIMIT,
            link=link,
            # a lock-step simulator waits for a stalled loop; a real arm must not
            stall_limit=None if self.sim is not None else STALL_LIMIT,
        )
        self.last_result = result
        if result.kind == "interrupted":  # Ctrl-C: the console ends
            self.closing.set()
        summary = f"{result.kind} ({result.reason}) after {result.duration:.1f} s"
        if not math.isnan(result.rms_error):
            summary += f", RMS tracking error {1e3 * result.rms_error:.1f} mm"
        self._arm_status("stopped", summary, last_run=summary, error=None)
        if not result.ok:
            self.status(error=f"the run ended: {result.reason}")

    def _calibration(self, plan_name: str, plan) -> None:
        from jaxcomp.identify.recorder import record

        self.job = "calibration"
        out = next_folder(self.out, "calibration")
        out.mkdir(parents=True, exist_ok=True)
        feed = self.link.feed if self.link is not None else None
        self._arm_status("calibrating", f"{plan_name} plan, {len(plan.sweeps)} sweeps")
        last = [0.0]

        def on_state(state, done: float) -> None:
            if self.stop.is_set():
                raise _Stopped
            if feed is not None and feed.state("calibrating", state, self._base_pose()):
                if done - last[0] >= 0.01:
                    last[0] = done
                    self.status(progress=done)

        try:
            rec = record(
                self.arm,
                plan,
                out / "recording.npz",
                model=self.robot,
                progress=False,
                on_state=on_state,
            )
        except _Stopped:
            self._arm_status("stopped", "calibration stopped (the finished sweeps are kept)")
            return
        self.status(progress=1.0)
        self.fitting = True
        threading.Thread(target=self._fit, args=(rec, out), daemon=True).start()

    def _fit(self, rec, out: Path) -> None:
        """The joint fit on a thread of its own (the arm holds meanwhile), then the
        controller with the new params (compiled here, swapped in when ready)."""
        from jaxcomp.control.impedance import make_impedance_controller
        from jaxcomp.identify import fit as fit_checked
        from jaxcomp.plausibility import checked_arm_params

        try:
            self.status(state="fitting", detail=f"{rec.n_samples} samples")
            params = fit_checked([rec], "jax")
            params.save(out / "params.json")
            controller = make_impedance_controller(
                self.arm_robot, checked_arm_params(params, self.arm_robot), self.controller.gains
            )
            controller.compile()
            self.controller = controller
            self.params_name = str(out / "params.json")
            self._arm_status("holding", f"fitted: {out / 'params.json'}")
        except JaxcompError as exc:
            self.status(state="holding", error=f"the fit was refused: {exc}")
        except Exception as exc:  # noqa: BLE001 - shown on the page
            log.exception("the fit failed")
            self.status(state="holding", error=f"the fit failed: {type(exc).__name__}: {exc}")
        finally:
            self.fitting = False


def simulated_operator(
    out: str | Path, model: str = "mobile_gen3_lite", seed: int = 0, preset: str = "tracking"
) -> Operator:
    """An ``Operator`` of the simulated ``model`` (true robot drawn from ``seed``, its arm at
    'home') whose controller knows the true params (demos, tests, benchmarks); the controller
    is built, not compiled (``operator.controller.compile()``).

    Args:
        out: folder for its runs and calibrations.
        model: a built-in model name or a model file.
        seed: the true robot's draw and the simulator's noise.
        preset: the gains preset ("tracking", "paper").

    Returns:
        The ``Operator``, paced on the wall clock; no page yet (``serve``).
    """
    from jaxcomp.control.impedance import make_impedance_controller
    from jaxcomp.control.mount import arm_model
    from jaxcomp.control.presets import impedance_gains
    from jaxcomp.hardware import Simulator, TrueRobot
    from jaxcomp.plausibility import checked_arm_params
    from jaxcomp.robot import load_robot

    robot = load_robot(model)
    arm = arm_model(robot)
    truth = TrueRobot.draw(robot, seed)
    sim = Simulator(robot, truth, seed=seed, initial_pose="home")
    controller = make_impedance_controller(
        arm, checked_arm_params(truth.params, arm), impedance_gains(arm, preset)
    )
    base = sim.base if sim.has_base else None
    return Operator(sim.arm, base, sim, robot, controller, preset, Path(out))


class _Stopped(Exception):
    """The page stopped a calibration."""


__all__ = ["MODES", "RUN_LIMIT", "Operator", "next_folder", "simulated_operator"]
