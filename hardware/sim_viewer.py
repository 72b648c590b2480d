"""MuJoCo's passive viewer of a simulation, where a display exists.

``open_viewer`` opens it beside a running simulation; without a display (Linux with neither
``DISPLAY`` nor ``WAYLAND_DISPLAY``), or where MuJoCo's viewer cannot start (no GL, no GUI
toolkit), there is none and the simulation runs headless.
"""

from __future__ import annotations

import logging
import os
import sys

import mujoco

log = logging.getLogger(__name__)


def open_viewer(model: mujoco.MjModel, data: mujoco.MjData):
    """MuJoCo's passive viewer of a model and its data.

    Args:
        model, data: the simulation to show (the viewer reads them at each ``sync``).

    Returns:
        The viewer handle (``mujoco.viewer.launch_passive``), or None when there is no display
        or the viewer is unavailable (logged).
    """
    headless = sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )
    if headless:
        log.info("no display: simulating without a viewer")
        return None
    try:
        import mujoco.viewer

        return mujoco.viewer.launch_passive(model, data)
    except Exception as exc:  # no GL, no GUI toolkit ...
        log.info("viewer unavailable (%s): simulating without it", exc)
        return None
