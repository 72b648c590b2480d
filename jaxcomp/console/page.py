"""The console's controls and live plots (viser GUI), in the page's process.

Every control sends one command (``send(name, args)``) to the control process, which
validates it as the command line does and replies; the reply (or its error, the CLI's
``error:`` line) shows under the controls. What the page shows comes from the frames
(``feed.FrameLayout``) and the status the control process sends: the phase (holding, guidance,
tracking, calibrating), the arm's modes and faults, the identified ratios and friction, the
loop's missed deadlines and the frames the page was too slow for.

Plots (the last ``WINDOW`` s at ``POINTS_PER_S`` points a second, redrawn every ``DRAW_EVERY``
frames: 5 Hz; each redraw costs the browser time per point, and a browser rendering in
software, e.g. a phone's or a headless one, falls behind at 10 Hz with 300 points a plot): one
joint's measured current against the model's prediction (their difference is the external
torque), the external force and its band (world frame), the tracking error, and the histogram
of the loop's periods.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from jaxcomp.console.feed import PHASE_NAMES, RATE, FrameLayout

#: s of history in the time plots.
WINDOW = 10.0
#: Points a second the time plots show (of the 30 frames a second).
POINTS_PER_S = 10
#: Frames between two redraws of the plots and the live line (5 Hz at 30 frames a second).
DRAW_EVERY = 6
#: Loop period histogram: bin edges, us.
PERIOD_EDGES = np.concatenate([np.arange(0.0, 2050.0, 50.0), [np.inf]])
_X = {"time": False}


def _plot(plot, x: np.ndarray, *ys: np.ndarray) -> None:
    """New data for a uPlot ``plot``, its y range set here: uPlot takes NaN (a gap: nothing
    drawn) for a number and its own range then fails, so the range comes from the finite
    values, rounded out to a step of 1, 2 or 5 times a power of ten. A new range rebuilds the
    chart in the browser: it is sent only when the data leave the range or fill less than a
    third of it."""
    finite = np.concatenate([y[np.isfinite(y)] for y in ys])
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    old = (plot.scales or {}).get("y", {}).get("range")
    if old is not None and old[0] <= lo and hi <= old[1] and 3 * (hi - lo) >= old[1] - old[0]:
        plot.data = (x, *ys)
        return
    span = max(hi - lo, 1e-3, 0.05 * max(abs(lo), abs(hi)))
    step = 10.0 ** np.floor(np.log10(span / 4))
    step *= next(m for m in (1, 2, 5, 10) if span / (m * step) <= 5)
    y_range = [float(np.floor(lo / step) * step), float(np.ceil(hi / step) * step)]
    if y_range[1] <= y_range[0]:
        y_range[1] = y_range[0] + step
    scales = {"x": _X, "y": {"auto": False, "range": y_range}}
    if plot.scales != scales:
        plot.scales = scales
    plot.data = (x, *ys)


def _series(label: str, color: str, dash: bool = False) -> dict:
    s = {"label": label, "stroke": color, "width": 1.5}
    if dash:
        s["dash"] = [6, 4]
    return s


class Page:
    """The GUI of one console (see the module doc) on ``server`` (a ``viser.ViserServer``).

    ``setup``: the control process's description (``link.ConsoleLink``): title, joints,
    controls ("console": everything; "control": a ``jaxcomp control`` run, live gains and
    stop; "calibrate": a ``jaxcomp calibrate`` run, stop), gains and their limits, plans.
    """

    def __init__(self, server, setup: dict, send: Callable[[str, dict], None]):
        self.server, self.send = server, send
        gui = server.gui
        self.layout = FrameLayout(len(setup["joints"]))
        self.joints = tuple(setup["joints"])
        controls = setup.get("controls", "console")
        gui.configure_theme(
            control_layout="collapsible", control_width="medium", show_share_button=False
        )
        gui.add_markdown(f"**jaxcomp console** — {setup.get('title', '')}")
        self.status = gui.add_markdown("connecting ...")
        self.live = gui.add_markdown("")
        self.message = gui.add_markdown("")
        gains = setup.get("gains", {})
        limits = setup.get("limits", {})
        with gui.add_folder("Drive"):
            if controls == "console":
                self.mode = gui.add_dropdown(
                    "mode", ("guidance", "tracking"), initial_value="guidance"
                )
                self.trajectory = gui.add_text("trajectory", initial_value="static")
                self.start = gui.add_button("Start", color="green")
                self.start.on_click(lambda _: self._start())
            if controls in ("console", "control"):
                self.stiffness = gui.add_number(
                    "stiffness N/m",
                    initial_value=float(gains.get("stiffness", 0.0)),
                    step=10.0,
                    hint=f"0-{limits.get('stiffness', 0):.4g} N/m, every axis",
                )
                self.damping = gui.add_number(
                    "damping N s/m",
                    initial_value=float(gains.get("damping", 0.0)),
                    step=1.0,
                    hint=f"0-{limits.get('damping', 0):.4g} N s/m, every axis",
                )
                self.friction = gui.add_checkbox(
                    "friction compensation", initial_value=bool(gains.get("friction", True))
                )
                self.apply = gui.add_button("Apply gains")
                self.apply.on_click(lambda _: self._gains())
                self.friction.on_update(lambda _: self._gains())
            self.stop = gui.add_button("Stop", color="red")
            self.stop.on_click(lambda _: self.send("stop", {}))
            if controls == "console":
                self.clear = gui.add_button("Clear faults")
                self.clear.on_click(lambda _: self.send("clear_faults", {}))
        if controls in ("console", "calibrate"):
            with gui.add_folder("Calibrate"):
                if controls == "console":
                    plans = tuple(setup.get("plans", ("short", "default")))
                    self.plan = gui.add_dropdown("plan", plans, initial_value=plans[0])
                    self.calibrate = gui.add_button("Calibrate, then fit")
                    self.calibrate.on_click(
                        lambda _: self.send("calibrate", {"plan": self.plan.value})
                    )
                self.progress = gui.add_progress_bar(0.0)
        self.panel = gui.add_panel()
        with self.panel.add_tab("Live"):
            self.joint = gui.add_dropdown(
                "joint", self.joints, initial_value=self.joints[min(1, len(self.joints) - 1)]
            )
            empty = (np.zeros(2), np.full(2, np.nan))
            self.current_plot = gui.add_uplot(
                (*empty, np.full(2, np.nan)),
                (_series("t s", ""), _series("measured A", "#1f77b4"),
                 _series("model A", "#ff7f0e", dash=True)),
                title="current against the model", scales={"x": _X}, aspect=2.3,
            )  # fmt: skip
            self.force_plot = gui.add_uplot(
                (*empty, *(np.full(2, np.nan),) * 3),
                (_series("t s", ""), _series("Fx N", "#d62728"), _series("Fy N", "#2ca02c"),
                 _series("Fz N", "#1f77b4"), _series("band N", "#999999", dash=True)),
                title="external force (world)", scales={"x": _X}, aspect=2.3,
            )  # fmt: skip
            self.error_plot = gui.add_uplot(
                empty,
                (_series("t s", ""), _series("error mm", "#9467bd")),
                title="tracking error |ee - target|", scales={"x": _X}, aspect=2.3,
            )  # fmt: skip
            centres = 0.5 * (PERIOD_EDGES[:-2] + PERIOD_EDGES[1:-1])
            self.period_plot = gui.add_uplot(
                (centres, np.zeros(len(centres))),
                (_series("period us", ""), {"label": "log10(1 + cycles)", "stroke": "#17becf",
                                            "width": 2, "points": {"show": True, "size": 4}}),
                title="loop period histogram", scales={"x": _X}, aspect=2.3,
            )  # fmt: skip
        self.panel.dock_left()
        self.panel.set_width(380)
        self._hist = np.zeros(len(PERIOD_EDGES) - 1, dtype=np.int64)
        self._hist_phase = None
        cap = int(WINDOW * 30) + 1
        self._t = np.full(cap, np.nan)
        self._rows = np.full((cap, self.layout.width), np.nan)
        self._i = 0
        self._frames = 0
        self._state: dict = {}
        self.last = None

    # ---- commands
    def _start(self) -> None:
        self.send(
            "start",
            {
                "mode": self.mode.value,
                "trajectory": self.trajectory.value,
                "stiffness": self.stiffness.value,
                "damping": self.damping.value,
                "friction": self.friction.value,
            },
        )

    def _gains(self) -> None:
        self.send(
            "gains",
            {
                "stiffness": self.stiffness.value,
                "damping": self.damping.value,
                "friction": self.friction.value,
            },
        )

    def reply(self, name: str, ok: str | None, error: str | None) -> None:
        """Show the control process's answer to command ``name``.

        Args:
            name: the command.
            ok: what its handler returned, shown after ``name`` (None or empty: nothing).
            error: its error message (None: it succeeded).
        """
        if error is not None:
            self.message.content = f"<span style='color:#c00'>**error:** {error}</span>"
        else:
            self.message.content = f"{name}: {ok}" if ok else ""

    def set_status(self, status: dict) -> None:
        """What the control process reports: state, arm modes, faults, params, progress.

        Args:
            status: fields updating those shown so far: state, detail, arm_modes,
                base_stopped, faults (list), ratio (n,) A/(N m) and friction (n,) A, params
                (their source), progress 0-1, last_run, error, gains {"stiffness": N/m,
                "damping": N s/m}.
        """
        self._state.update(status)
        s = self._state
        lines = [f"**{s.get('state', '?')}**" + (f" — {s['detail']}" if s.get("detail") else "")]
        if s.get("arm_modes"):
            lines.append(
                f"arm: {s['arm_modes']}" + (", base stopped" if s.get("base_stopped") else "")
            )
        faults = s.get("faults") or []
        lines.append("faults: " + ("; ".join(faults) if faults else "none"))
        if s.get("ratio") is not None:
            ratio = " ".join(f"{x:.3f}" for x in s["ratio"])
            friction = " ".join(f"{x:.2f}" for x in s["friction"])
            lines.append(
                f"params ({s.get('params', '')}): ratio A/(N m) {ratio}; friction A {friction}"
            )
        if s.get("last_run"):
            lines.append(f"last run: {s['last_run']}")
        self.status.content = "  \n".join(lines)
        if "progress" in status and hasattr(self, "progress"):
            self.progress.value = 100.0 * float(status["progress"])
        if "error" in status and status["error"]:
            self.message.content = f"<span style='color:#c00'>**error:** {status['error']}</span>"
        if "gains" in status and hasattr(self, "stiffness"):
            self.stiffness.value = float(status["gains"]["stiffness"])
            self.damping.value = float(status["gains"]["damping"])

    # ---- frames
    def frames(self, frames: np.ndarray, dropped: int) -> None:
        """Take new frames (oldest first); redraw the plots every ``DRAW_EVERY``-th call that
        brings frames (the period histogram every second redraw).

        Args:
            frames: (k, width) frames (``feed.FrameLayout``), oldest first; k may be 0.
            dropped: frames the ring overwrote before they were read, so far (shown).
        """
        lay = self.layout
        for f in frames:
            phase = f[1]
            if self._hist_phase != phase and phase in (1.0, 2.0):  # a new run: a new histogram
                self._hist[:] = 0
            self._hist_phase = phase
            m = int(f[lay.slices["n_periods"]][0]) if np.isfinite(f[4]) else 0
            if m:
                per = f[lay.slices["periods"]][:m]
                self._hist += np.histogram(per, PERIOD_EDGES)[0]
            self._rows[self._i % len(self._t)] = f
            self._t[self._i % len(self._t)] = lay.get(f, "t")
            self._i += 1
        if not len(frames):
            return
        self.last = frames[-1]
        self._frames += 1
        if self._frames % DRAW_EVERY == 0:
            self._draw(dropped)

    def _window(self) -> tuple[np.ndarray, np.ndarray]:
        k = min(self._i, len(self._t))
        stride = max(int(round(RATE / POINTS_PER_S)), 1)
        order = np.arange(self._i - 1, self._i - k - 1, -stride)[::-1] % len(self._t)
        return self._t[order], self._rows[order]

    def _draw(self, dropped: int) -> None:
        lay, last = self.layout, self.last
        t, rows = self._window()
        j = self.joints.index(self.joint.value)
        cur = rows[:, lay.slices["current"]][:, j]
        model = rows[:, lay.slices["current_model"]][:, j]
        _plot(self.current_plot, t, cur, model)
        w, b = rows[:, lay.slices["wrench"]], rows[:, lay.slices["wrench_band"]]
        _plot(self.force_plot, t, w[:, 0], w[:, 1], w[:, 2], np.linalg.norm(b, axis=1))
        err = 1e3 * np.linalg.norm(
            rows[:, lay.slices["ee"]] - rows[:, lay.slices["target"]], axis=1
        )
        _plot(self.error_plot, t, err)
        if self._frames % (2 * DRAW_EVERY) == 0:
            counts = self._hist[:-1].astype(float)
            _plot(self.period_plot, self.period_plot.data[0], np.log10(1.0 + counts))
        phase = PHASE_NAMES.get(float(last[1]), "?")
        q = lay.get(last, "q")
        parts = [f"t = {lay.get(last, 't'):.2f} s", phase]
        if np.isfinite(last[2]):
            parts.append(
                f"missed deadlines {int(last[2])} of {int(last[3])} "
                f"({100 * last[2] / max(last[3], 1):.3f} %)"
            )
        e = err[-1] if len(err) else np.nan
        if np.isfinite(e):
            parts.append(f"error {e:.1f} mm")
        force = lay.get(last, "wrench")
        if np.all(np.isfinite(force)):
            band = lay.get(last, "wrench_band")
            parts.append(
                f"force ({', '.join(f'{x:.1f}' for x in force)}) ± "
                f"({', '.join(f'{x:.1f}' for x in band)}) N"
            )
        parts.append(f"frames dropped {dropped}")
        self.live.content = " · ".join(parts) + "  \nq (rad): " + " ".join(f"{x:+.3f}" for x in q)


__all__ = ["DRAW_EVERY", "PERIOD_EDGES", "POINTS_PER_S", "WINDOW", "Page"]
