"""The faults injected into the Kortex emulator: what comes when, in emulated time.

An ``InjectionSchedule`` holds the events ``KortexEmulator.inject_*`` asked for (stalls, stale
feedback, actuator and arm faults, lost replies or commands, configuration timeouts). The
emulator asks at each exchange whether one is due: a one-shot event once its time has come
(``due``; stale feedback lasts its ``seconds``), a counted one for each of its ``count`` calls
(``take``). Times in s of the emulator's clock.
"""

from __future__ import annotations

from dataclasses import dataclass

#: What ``inject_lost`` loses: the reply (the command was applied), the command (it never
#: arrived) or the send itself (a client error at once, nothing sent).
LOST_KINDS = ("reply", "command", "client")


@dataclass
class Injection:
    """One injected event.

    Attributes: at (s, when it comes), kind ("stall", "stale", "fault", "arm_fault", "lost",
    "config_timeout"), seconds (s, of a stall or of stale feedback), device (the faulting
    actuator's id), bits (fault bits), count (calls a counted event still affects), what (of
    a loss: one of ``LOST_KINDS``), done (used up).
    """

    at: float
    kind: str
    seconds: float = 0.0
    device: int = 0
    bits: int = 0
    count: int = 1
    what: str = ""
    done: bool = False


class InjectionSchedule:
    """The injected events of one emulator, in the order they were asked for."""

    def __init__(self):
        self._events: list[Injection] = []

    def add(self, event: Injection) -> None:
        """Schedule an event.

        Args:
            event: the ``Injection`` to come.
        """
        self._events.append(event)

    def due(self, kind: str, t: float) -> Injection | None:
        """The first event of ``kind`` whose time has come by ``t`` s, now used up (stale
        feedback: while ``t`` is within its ``seconds``, used up after).

        Args:
            kind: the event's kind. t: the emulated time, s.

        Returns:
            The event, or None.
        """
        for inj in self._events:
            if inj.kind == kind and not inj.done and t >= inj.at:
                if kind == "stale":
                    if t < inj.at + inj.seconds:
                        return inj
                    inj.done = True
                    continue
                inj.done = True
                return inj
        return None

    def take(self, kind: str, t: float) -> Injection | None:
        """A due counted event of ``kind``, one of its counts used up.

        Args:
            kind: the event's kind. t: the emulated time, s.

        Returns:
            The event, or None.
        """
        for inj in self._events:
            if inj.kind == kind and not inj.done and t >= inj.at - 1e-9:
                inj.count -= 1
                inj.done = inj.count <= 0
                return inj
        return None
