"""Physical and timing constants shared by every room of jaxcomp (SI units)."""

CONTROL_PERIOD = 0.001
"""s, the period of the arm's control loop and of every recording (1 kHz)."""

CONTROL_RATE = 1000.0
"""Hz, 1 / CONTROL_PERIOD."""

STANDARD_GRAVITY = (0.0, 0.0, -9.81)
"""m/s^2, gravity in the base frame of an upright-mounted robot."""
