"""The control process's end of the browser console.

``ConsoleLink`` starts the page's server (``server.serve``) in a process of its own, hands it
frames through a ``FrameRing`` (its ``feed``: the ``LoopMonitor`` of a control run, or
``Feed.state`` from any other loop) and status lines (``status``), and runs the page's
commands through ``handler`` on a thread of its own, replying with its message or its
``JaxcompError`` (the text the command line prints after ``error:``).

When the last browser disconnects, or the page's process dies, ``on_lost`` decides: "continue"
(the run goes on, a warning is logged) or "stop" (``on_stop`` is called: the run stops safely,
arm in position mode, base stopped).
"""

from __future__ import annotations

import logging
import os
import secrets
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Listener
from typing import Any

from jaxcomp.console.feed import Feed, FrameLayout
from jaxcomp.console.ring import FrameRing
from jaxcomp.errors import InputError, JaxcompError

log = logging.getLogger(__name__)

#: What to do when the page goes away (``--on-disconnect``).
ON_LOST = ("continue", "stop")
#: s to wait for the page's server to start.
START_TIMEOUT = 120.0


class ConsoleLink:
    """The browser console of one robot (see the module doc).

    Args:
        robot: the whole model the page draws (a mobile manipulator with its base joints).
        joints: the names of the arm's joints, in the order of the frames' q.
        base_joints: the base's (x, y, yaw) joints, or () without a base.
        handler: ``handler(name, args) -> str | None`` runs one command from the page (on
            the link's thread); a ``JaxcompError`` is shown on the page as an error.
        port, host: where the page is served (a busy port: the next free one).
        title: the page's title line. controls: "console", "control" or "calibrate"
            (``page.Page``). gains, limits: the initial live gains and their limits.
            plans: the calibration plans the page offers ("console" controls), the first chosen.
        on_lost: "continue" or "stop" (``ON_LOST``); on_stop: what "stop" calls.
    """

    def __init__(
        self,
        robot,
        joints: tuple[str, ...],
        base_joints: tuple[str, ...] = (),
        *,
        handler: Callable[[str, dict], str | None],
        port: int = 8080,
        host: str = "127.0.0.1",
        title: str = "",
        controls: str = "console",
        gains: dict | None = None,
        limits: dict | None = None,
        plans: tuple[str, ...] = ("short", "default"),
        on_lost: str = "continue",
        on_stop: Callable[[], None] | None = None,
    ):
        if on_lost not in ON_LOST:
            raise InputError(f"on_lost must be one of {', '.join(ON_LOST)}, got {on_lost!r}")
        if not (isinstance(port, int) and 0 < port < 65536):
            raise InputError(f"--port must be a TCP port 1-65535, got {port!r}")
        self.handler, self.on_lost, self.on_stop = handler, on_lost, on_stop
        layout = FrameLayout(len(joints))
        self.ring = FrameRing.create(layout.width)
        self.feed = Feed(self.ring, len(joints))
        self.clients = 0
        self.seen_client = threading.Event()
        self.lost: str | None = None
        self._lock = threading.Lock()
        self._ready = threading.Event()
        self.port: int | None = None
        setup = {
            "ring": str(self.ring.path),
            "model": robot.reference,
            "model_joints": list(robot.controlled_joints),
            "joints": list(joints),
            "base_joints": list(base_joints),
            "host": host,
            "port": port,
            "title": title,
            "controls": controls,
            "gains": gains or {},
            "limits": limits or {},
            "plans": list(plans),
        }
        # a process of its own, started afresh (not forked from one running JAX threads),
        # reached through an authenticated local socket
        key = secrets.token_bytes(32)
        self._listener = Listener(family="AF_UNIX", authkey=key)
        env = dict(os.environ, JAXCOMP_CONSOLE_KEY=key.hex())
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "jaxcomp.console.server", self._listener.address],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )
        self._setup = setup
        self._conn = None
        self._thread = threading.Thread(target=self._listen, name="jaxcomp-console", daemon=True)
        self._thread.start()
        end = time.monotonic() + START_TIMEOUT
        while not self._ready.wait(0.1) and time.monotonic() < end:
            if self._proc.poll() is not None:  # it died before it served
                break
        if self.port is None:
            self.close()
            raise InputError(
                "the console's page server did not start (its error, if any, is above)"
            )
        self.host = "localhost" if host in ("127.0.0.1", "0.0.0.0") else host
        self.url = f"http://{self.host}:{self.port}"

    # ---- to the page
    def _send(self, message: dict) -> None:
        with self._lock:
            if self._conn is None:
                return
            try:
                self._conn.send(message)
            except (OSError, ValueError):  # the page's process is gone
                pass

    def status(self, **fields: Any) -> None:
        """Show ``fields`` on the page.

        Args:
            fields: the status lines to show, by name (state, detail, arm_modes, faults, ratio,
                friction, params, progress, last_run, error, gains), JSON-able.
        """
        self._send({"status": fields})

    # ---- from the page
    def _listen(self) -> None:
        try:
            conn = self._listener.accept()
            with self._lock:
                self._conn = conn
            conn.send(self._setup)
            while True:
                msg = self._conn.recv()
                if "event" in msg:
                    self._event(msg)
                elif "cmd" in msg:
                    self._command(msg["cmd"], msg.get("args") or {})
        except (EOFError, OSError):
            pass
        except Exception:  # noqa: BLE001 - e.g. a wrong key: the page never starts
            log.exception("the console's page server could not connect")
        self._ready.set()
        if self.lost is None and not getattr(self, "_closing", False):
            self._lose("the console's page server stopped")

    def _event(self, msg: dict) -> None:
        if msg["event"] == "ready":
            self.port = int(msg["port"])
            self._ready.set()
        elif msg["event"] == "clients":
            self.clients = int(msg["count"])
            if self.clients:
                self.seen_client.set()
            elif self.seen_client.is_set():
                self._lose("the browser disconnected")

    def _command(self, name: str, args: dict) -> None:
        try:
            ok = self.handler(name, args)
            self._send({"reply": name, "ok": ok})
        except JaxcompError as exc:
            self._send({"reply": name, "error": str(exc)})
        except Exception as exc:  # noqa: BLE001 - the page shows it; the link goes on
            log.exception("console command %s failed", name)
            self._send({"reply": name, "error": f"{type(exc).__name__}: {exc}"})

    def _lose(self, why: str) -> None:
        if self.on_lost == "stop" and self.on_stop is not None:
            log.warning("%s: stopping (--on-disconnect stop)", why)
            self.lost = why
            self.on_stop()
        else:
            log.warning("%s: control goes on (--on-disconnect continue)", why)

    # ---- lifetime
    @property
    def alive(self) -> bool:
        """Whether the page's process runs."""
        return self._proc.poll() is None

    @property
    def server_pid(self) -> int:
        """The process id of the page's server (e.g. to measure its CPU time)."""
        return self._proc.pid

    def close(self) -> None:
        """Stop the page's process and remove the ring."""
        self._closing = True
        self._send({"quit": True})
        try:
            self._proc.wait(10.0)
        except subprocess.TimeoutExpired:
            self._proc.terminate()
            self._proc.wait(5.0)
        self._listener.close()  # unblocks an accept still waiting
        with self._lock:
            if self._conn is not None:
                self._conn.close()
        self.ring.close()

    def __enter__(self) -> ConsoleLink:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["ON_LOST", "ConsoleLink"]
