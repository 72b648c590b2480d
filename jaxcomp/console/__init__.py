"""The operator console in the browser: ``jaxcomp console`` and ``--console`` of ``jaxcomp
control`` and ``jaxcomp calibrate``.

Wiring, like the command line: it shows and drives what ``control``, ``identify`` and
``hardware`` do, and holds no maths of its own.

- ``ring``: a ring buffer of numeric frames shared by two processes (never blocks the loop);
- ``feed``: the frames (layout) and the ``Feed`` that writes them (a ``LoopMonitor``);
- ``link``: the control process's end: the page's process, status, the page's commands;
- ``server``, ``page``, ``scene``: the page's process: a viser server, its controls and
  plots, the 3D robot from its MuJoCo model;
- ``operator``: ``jaxcomp console``'s robot, one job at a time (hold, run, calibrate, fit).

The page (viser: three.js and uPlot in the browser, a websocket to Python) runs in a process
of its own, fed at most 30 times a second from the ring: the 1 kHz loop never waits for it.
"""
