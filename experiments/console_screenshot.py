"""The screenshot of the browser console in the README (docs/console.png).

``jaxcomp console`` on the simulated mobile Gen3 Lite (its true params, the tracking gains),
driven through its page in headless Chromium as a person would: guidance mode along a circle
(in the base's frame: the arm moves, the base follows) is started from the page, a person's
push (a constant force on the end effector, world frame) acts, and the page is captured while
the push lasts. The control thread runs under SCHED_FIFO when the OS allows it.

Run: python experiments/console_screenshot.py [--out docs/console.png] [--push FX,FY,FZ]
"""

import os

os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import argparse  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

from jaxcomp.console.operator import simulated_operator  # noqa: E402
from jaxcomp.control.timing import configure_jax_for_control, realtime_priority  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/console.png")
    ap.add_argument("--push", default="0,8,6", help="N, world frame")
    ap.add_argument("--width", type=int, default=1500)
    ap.add_argument("--height", type=int, default=900)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    configure_jax_for_control()
    push = tuple(float(x) for x in args.push.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        operator = simulated_operator(tmp)
        operator.controller.compile()
        sim = operator.sim
        link = operator.serve(8790, title="mobile_gen3_lite (simulator)")

        def control():
            with realtime_priority(50):
                operator.run()

        thread = threading.Thread(target=control, daemon=True)
        thread.start()
        chromium = shutil.which("chromium") or shutil.which("chromium-browser")
        with sync_playwright() as play:
            browser = play.chromium.launch(
                executable_path=chromium,
                args=["--enable-unsafe-swiftshader", "--use-angle=swiftshader"],
            )
            page = browser.new_page(viewport={"width": args.width, "height": args.height})
            page.goto(link.url)
            page.get_by_text("holding").first.wait_for(timeout=60_000)
            row = "//label[normalize-space()='trajectory']/ancestor::div[contains(@class, 'Flex')]"
            page.locator(f"xpath={row}[1]//input").fill("circle:r=0.15,v=0.1")
            page.get_by_role("button", name="Start").click()
            page.get_by_text("guidance mode, circle").first.wait_for(timeout=60_000)
            time.sleep(5.0)
            sim.set_wrench(push)
            time.sleep(3.0)
            for close in page.get_by_role("button", name="Close").all():  # notifications
                close.click()
            time.sleep(1.0)
            page.screenshot(path=args.out)
            sim.set_wrench()
            browser.close()
        operator.close()
        thread.join(30)
        link.close()
    sim.close()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
