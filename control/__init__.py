"""Current-based impedance control of the arm and the base follower."""
