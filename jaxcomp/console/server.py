"""The page's process: a viser server showing the robot and its plots, fed from a frame ring.

``serve`` runs in a process of its own (``link.ConsoleLink`` starts it), so the page's work
(forward kinematics, messages to the browser, plots) never holds the control process's
interpreter lock: the 1 kHz loop only copies a frame into the shared ring, 30 times a second.
It reads the ring at ``feed.RATE``, draws what is new, sends the page's commands and the
number of connected browsers to the control process through ``conn``, and shows what comes
back (status, replies). It ends when the control process says so or goes away.
"""

from __future__ import annotations

import os
import threading
import time

from jaxcomp.console.feed import RATE, FrameLayout
from jaxcomp.console.ring import FrameRing


def serve(conn, setup: dict) -> None:
    """Serve the console page (see the module doc); ``setup`` from ``ConsoleLink``.

    Args:
        conn: the connection to the control process (``multiprocessing.connection``).
        setup: the control process's description: the ring's path, the model and its
            controlled joints, the arm's and the base's joints, host, port, and what ``Page``
            reads.
    """
    import logging

    import viser

    from jaxcomp.console.page import Page
    from jaxcomp.console.scene import RobotScene
    from jaxcomp.robot import load_robot

    logging.getLogger("websockets").setLevel(logging.ERROR)
    try:
        os.nice(5)  # below the control process, whatever its scheduling
    except OSError:
        pass
    ring = FrameRing(setup["ring"])
    lock = threading.Lock()

    def send(message: dict) -> None:
        with lock:
            try:
                conn.send(message)
            except (OSError, ValueError):  # the control process is gone
                pass

    server = viser.ViserServer(host=setup["host"], port=setup["port"], verbose=False)
    page = Page(server, setup, lambda name, args: send({"cmd": name, "args": args}))
    robot = load_robot(setup["model"], joints=setup["model_joints"])
    scene = RobotScene(server, robot, setup["joints"], setup["base_joints"])
    server.initial_camera.position = (1.0, -1.25, 0.85)
    server.initial_camera.look_at = (0.3, 0.0, 0.35)
    clients: set[int] = set()

    @server.on_client_connect
    def _(client) -> None:
        clients.add(client.client_id)
        send({"event": "clients", "count": len(clients)})

    @server.on_client_disconnect
    def _(client) -> None:
        clients.discard(client.client_id)
        send({"event": "clients", "count": len(clients)})

    quit_ = threading.Event()

    def listen() -> None:
        try:
            while True:
                msg = conn.recv()
                if msg.get("quit"):
                    break
                if "status" in msg:
                    page.set_status(msg["status"])
                if "reply" in msg:
                    page.reply(msg["reply"], msg.get("ok"), msg.get("error"))
        except (EOFError, OSError):
            pass
        finally:
            quit_.set()

    threading.Thread(target=listen, name="jaxcomp-console-listen", daemon=True).start()
    send({"event": "ready", "port": server.get_port(), "geoms": scene.geoms})
    lay = FrameLayout(len(setup["joints"]))
    tick = time.perf_counter()
    try:
        while not quit_.is_set():
            frames = ring.read()
            if len(frames):
                last = frames[-1]
                with server.atomic():
                    scene.pose(lay.get(last, "q"), lay.get(last, "base"))
                    scene.markers(
                        lay.get(last, "target"),
                        lay.get(last, "ee"),
                        lay.get(last, "wrench"),
                        lay.get(last, "wrench_band"),
                    )
                    page.frames(frames, ring.dropped)
            tick += 1.0 / RATE
            time.sleep(max(tick - time.perf_counter(), 0.0))
            tick = max(tick, time.perf_counter() - 1.0)  # a slow page does not race after
    finally:
        server.stop()
        ring.close()


def main() -> None:
    """``python -m jaxcomp.console.server ADDRESS``: connect to the control process (key in
    ``$JAXCOMP_CONSOLE_KEY``), take the setup, serve."""
    import signal
    import sys
    from multiprocessing.connection import Client

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is for the control process: it ends us
    key = bytes.fromhex(os.environ.pop("JAXCOMP_CONSOLE_KEY"))
    conn = Client(sys.argv[1], family="AF_UNIX", authkey=key)
    serve(conn, conn.recv())


if __name__ == "__main__":
    main()


__all__ = ["main", "serve"]
