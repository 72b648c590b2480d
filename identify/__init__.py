"""Identification of current/torque ratios, friction losses and centre-of-mass errors."""
