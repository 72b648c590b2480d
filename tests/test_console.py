"""The browser console (``jaxcomp console``): its frame ring, and the page in a real headless
browser (the distribution's Chromium, driven by playwright) on the simulated mobile Gen3 Lite.

One console (simulator, controller, the page's server process) and one browser serve the
module; the browser tests run in order: the page shows the arm and live plots; tracking mode
and a gain from the page take effect in the simulator (the deflection under a push is F / K);
a bad gain is refused with the command line's error; stop leaves the arm in position mode.
"""

from __future__ import annotations

import shutil
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from jaxcomp.console.feed import Feed, FrameLayout
from jaxcomp.console.ring import FrameRing
from jaxcomp.hardware import ControlMode

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

# one worker runs the module in order: the browser tests share one console (module fixture),
# and the stop test stops the run that the tracking test started
pytestmark = pytest.mark.xdist_group("console")


# ----------------------------------------------------------------------------- the ring


def test_ring_hands_over_frames_and_counts_those_it_dropped():
    ring = FrameRing.create(4, slots=8)
    reader = FrameRing(ring.path)
    for i in range(5):
        ring.write(np.full(4, float(i)))
    np.testing.assert_array_equal(reader.read()[:, 0], np.arange(5))
    assert reader.read().shape == (0, 4) and reader.dropped == 0
    for i in range(5, 25):  # a reader too slow for 20 frames: it keeps the newest 7
        ring.write(np.full(4, float(i)))
    np.testing.assert_array_equal(reader.read()[:, 0], np.arange(18, 25))
    assert reader.dropped == 13
    ring.write(np.array([1.0, 2.0]))  # short frames are padded with NaN
    np.testing.assert_array_equal(reader.read()[0], [1.0, 2.0, np.nan, np.nan])
    ring._seq[ring.written % 8] = 2 * ring.written + 1  # a frame caught half-written
    ring._head[1] += 1
    assert reader.read().shape == (0, 4) and reader.dropped == 14
    path = ring.path
    reader.close()
    ring.close()
    assert not path.exists()


def test_feed_frames_carry_the_recorded_row_and_loop_periods():
    from jaxcomp.control.run_link import MonitorStart
    from jaxcomp.control.timing import CycleTimer

    ring = FrameRing.create(FrameLayout(6).width)
    reader = FrameRing(ring.path)
    feed, lay = Feed(ring, 6), FrameLayout(6)
    timer = CycleTimer()
    feed.started(MonitorStart("tracking", "", {}, timer, 1.0))
    for k in range(40):
        timer.record(k * 1_000_000, k * 1_000_000 + 10, k * 1_000_000 + 20, (k + 1) * 1_000_000)
    row = np.arange(1.0 + 4 * 6 + 9 + 6 + 6)  # t | q dq current command | target ee base | ...
    feed.sample(40, row)
    frame = reader.read()[0]
    assert lay.get(frame, "phase") == 2.0 and lay.get(frame, "cycles") == 40
    assert lay.get(frame, "n_periods") == 39
    np.testing.assert_array_equal(frame[lay["periods"]][:39], 1000.0)
    np.testing.assert_array_equal(frame[lay.row :], row)
    ring.close()


# ----------------------------------------------------------------------------- the page


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    """(page, operator, sim): ``jaxcomp console`` on the simulated mobile Gen3 Lite (true
    params, tracking gains) with its page open in headless Chromium."""
    if CHROMIUM is None:
        pytest.skip("no Chromium: .ci/run installs the distribution's (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    from jaxcomp.console.operator import simulated_operator

    operator = simulated_operator(tmp_path_factory.mktemp("console"))
    sim = operator.sim
    with ThreadPoolExecutor(1) as pool:  # the page's process starts while JAX compiles
        started = pool.submit(operator.serve, _free_port())
        play = sync_api.sync_playwright().start()
        browser = play.chromium.launch(
            executable_path=CHROMIUM,
            args=["--enable-unsafe-swiftshader", "--use-angle=swiftshader"],
        )
        operator.controller.compile()
        link = started.result()
    thread = threading.Thread(target=operator.run, daemon=True)
    thread.start()
    page = browser.new_page(viewport={"width": 1100, "height": 760})
    page.goto(link.url)
    try:
        yield page, operator, sim
    finally:
        operator.close()
        thread.join(30)
        browser.close()
        play.stop()
        link.close()
        sim.close()


def _wait(condition, timeout: float = 15.0, what: str = "") -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _live(page) -> str:
    return page.get_by_text("frames dropped").first.inner_text()


def _shot(element, tries: int = 5) -> bytes:
    """A screenshot of ``element``, taken again when the page redraws it meanwhile (the plots
    replace their nodes as points arrive)."""
    from playwright.sync_api import Error

    for _ in range(tries - 1):
        try:
            return element.screenshot()
        except Error:
            time.sleep(0.2)
    return element.screenshot()


def _steady_height(sim, timeout: float = 8.0) -> float:
    """The end effector's height (m) once it moves less than 0.2 mm in 0.2 s of simulated
    time (on a loaded machine the simulator runs slower than real time: a wait on the wall
    clock may end before the arm has settled)."""
    end = time.monotonic() + timeout
    t0, z0 = sim.data.time, sim.ee_position()[2]
    while True:
        time.sleep(0.05)
        t, z = sim.data.time, sim.ee_position()[2]
        if time.monotonic() > end:
            return float(z)
        if t - t0 >= 0.2:
            if abs(z - z0) < 2e-4:
                return float(z)
            t0, z0 = t, z


def _scene(page) -> np.ndarray:
    """The 3D view (the largest canvas, between the two panels), RGB."""
    import io

    from PIL import Image

    canvases = page.locator("canvas")
    boxes = [canvases.nth(i).bounding_box() for i in range(canvases.count())]
    box = max((b for b in boxes if b), key=lambda b: b["width"] * b["height"])
    shot = page.screenshot(clip=box)
    return np.asarray(Image.open(io.BytesIO(shot)).convert("RGB")).astype(int)


def test_page_shows_the_arm_and_live_plots(console):
    page, operator, sim = console
    page.get_by_text("holding").first.wait_for(timeout=30_000)
    first = _live(page)
    _wait(lambda: _live(page) != first, what="the live line to change")
    assert "t = " in first and "idle" in first
    rgb = _scene(page)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    assert ((r - b > 40) & (g - b > 20)).sum() > 300  # the base's yellow chassis
    assert ((r < 110) & (g < 110) & (b < 110)).sum() > 300  # wheels, joint housings
    plot = page.locator(".uplot").first  # current against the model
    assert "current against the model" in plot.inner_text()
    shots = [_shot(page.locator(".uplot").first) for _ in range(2) if not time.sleep(0.5)]
    assert shots[0] != shots[1]  # the measured current moves (sensor noise)


def test_tracking_and_a_gain_from_the_page_take_effect(console):
    page, operator, sim = console
    page.get_by_role("combobox", name="mode").click()
    page.get_by_role("option", name="tracking").click()
    page.get_by_label("stiffness").fill("250")
    page.get_by_role("button", name="Start").click()
    _wait(lambda: operator.job == "run" and sim.arm.modes[0] is ControlMode.CURRENT, what="run")
    page.get_by_text("tracking mode, static").first.wait_for(timeout=10_000)
    assert operator.tuning.values[0] == 250.0
    _wait(lambda: operator.tuning.applied == operator.tuning.version, what="the loop's gains")

    def deflection(force: float) -> float:
        sim.set_wrench((0.0, 0.0, force))  # N up, world
        time.sleep(0.5)
        pushed = _steady_height(sim)
        sim.set_wrench()
        time.sleep(0.5)
        return pushed - _steady_height(sim)  # m

    soft = deflection(8.0)
    assert soft == pytest.approx(8.0 / 250.0, rel=0.25)  # F / K
    page.get_by_label("stiffness").fill("500")
    page.get_by_role("button", name="Apply gains").click()
    _wait(lambda: operator.tuning.values[0] == 500.0, what="the new stiffness")
    _wait(lambda: operator.tuning.applied == operator.tuning.version, what="the loop's gains")
    stiff = deflection(8.0)
    assert stiff == pytest.approx(8.0 / 500.0, rel=0.25)
    # a gain beyond the safe range: refused with the command line's error, nothing changes
    page.get_by_label("stiffness").fill("5000")
    page.get_by_role("button", name="Apply gains").click()
    page.get_by_text("outside the safe range 0-1000 N/m").first.wait_for(timeout=10_000)
    assert operator.tuning.values[0] == 500.0


def test_stop_leaves_the_arm_in_position_mode(console):
    page, operator, sim = console
    if operator.job != "run":  # alone, or on a fresh console (a worker may run tests between)
        page.get_by_role("button", name="Start").click()
        _wait(lambda: operator.job == "run" and sim.arm.modes[0] is ControlMode.CURRENT,
              what="run")  # fmt: skip
    page.get_by_role("button", name="Stop").click()
    _wait(lambda: operator.job is None, what="the run to stop")
    assert all(m is ControlMode.POSITION for m in sim.arm.modes)
    np.testing.assert_array_equal(sim._limiter._cmd, 0.0)  # the base told to stop
    page.get_by_text("stopped").first.wait_for(timeout=10_000)
    page.get_by_text("arm: position").first.wait_for(timeout=10_000)
    assert operator.last_result is not None, f"the run ended in an error: {operator.last_error}"
    kind = operator.last_result.kind
    assert kind == "stopped", operator.last_result.reason
