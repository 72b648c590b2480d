"""Fault codes of the MJX closed loop: why a world went to POSITION mode.

The bits of ``ClosedLoopResult.fault_code``, one per cause (as the CPU Simulator and the
``Arm`` interface would stop): a joint at its limit, a current whose torque is beyond the
effort limit, a joint faster than ``overspeed``, a command refused before it is sent (NaN/inf
or beyond the arm's current limit), the policy asking to stop (e.g. its watchdog).
"""

FAULT_LIMIT, FAULT_EFFORT, FAULT_OVERSPEED, FAULT_REFUSED, FAULT_STOPPED = 1, 2, 4, 8, 16
FAULT_NAMES = {
    FAULT_LIMIT: "joint limit",
    FAULT_EFFORT: "effort limit",
    FAULT_OVERSPEED: "overspeed",
    FAULT_REFUSED: "command refused",
    FAULT_STOPPED: "stopped by the policy",
}


def fault_names(code: int) -> list[str]:
    """What a world's fault code says.

    Args:
        code: a world's ``ClosedLoopResult.fault_code``.

    Returns:
        The readable names of the bits set in ``code``, in bit order.
    """
    return [name for bit, name in FAULT_NAMES.items() if int(code) & bit]
