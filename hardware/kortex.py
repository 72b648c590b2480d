"""The real Kinova Gen3 Lite through Kinova's ``kortex_api`` (an optional extra).

``KortexArm`` is the ``Arm`` interface on Kortex low-level servoing: configuration over TCP
(port 10000), the 1 kHz cyclic channel over UDP (port 10001). Opening it creates the sessions,
switches the base to LOW_LEVEL_SERVOING, sends a first frame that echoes the measured
positions and puts every actuator (device ids 1-5 and 7) in POSITION mode. Every cycle it
advances ``frame_id`` (mod 65536), sets each actuator's ``command_id`` to it, sends the joint's
target in its mode (position deg, velocity deg/s, ``current_motor`` A) and, for joints not in
POSITION mode, echoes the measured position so that no following error arises.

A cycle fails safe (state faults, then ``HardwareFault``) on an actuator fault bit, on a
missed cycle (more than ``max_cycle_gap`` s since the previous one) and on stale feedback (no
new frame for ``stale_after`` s). Every exit path (normal, exception, Ctrl-C, fault) restores
POSITION mode on every actuator and SINGLE_LEVEL_SERVOING and closes the sessions.

``kortex_api`` is not on PyPI: install Kinova's wheel without its dependencies next to
protobuf 3.20 (``pip install --no-deps kortex_api-2.6.0.post3-py3-none-any.whl
"protobuf==3.20.*"``). Without an arm, run against ``KortexEmulator`` (``KortexArm.emulated``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

from jaxcomp.hardware.interface import Arm, ArmLimits, ArmState, ControlMode, HardwareFault
from jaxcomp.robot import Robot, load_robot

log = logging.getLogger(__name__)

DEVICE_IDS = (1, 2, 3, 4, 5, 7)
TCP_PORT, UDP_PORT = 10000, 10001
_MODE_NAME = {
    ControlMode.POSITION: "POSITION",
    ControlMode.VELOCITY: "VELOCITY",
    ControlMode.CURRENT: "CURRENT",
}


def import_kortex_api() -> SimpleNamespace:
    """The kortex_api classes and message modules the adapter uses (lazy import)."""
    try:
        from kortex_api.autogen.client_stubs.ActuatorConfigClientRpc import ActuatorConfigClient
        from kortex_api.autogen.client_stubs.BaseClientRpc import BaseClient
        from kortex_api.autogen.client_stubs.BaseCyclicClientRpc import BaseCyclicClient
        from kortex_api.autogen.messages import (
            ActuatorConfig_pb2,
            Base_pb2,
            BaseCyclic_pb2,
            Session_pb2,
        )
        from kortex_api.Exceptions.KServerException import KServerException
        from kortex_api.RouterClient import RouterClient, RouterClientSendOptions
        from kortex_api.SessionManager import SessionManager
        from kortex_api.TCPTransport import TCPTransport
        from kortex_api.UDPTransport import UDPTransport
    except ImportError as exc:
        raise ImportError(
            "the Kortex adapter needs Kinova's kortex_api, which is not on PyPI: download "
            "kortex_api-2.6.0.post3-py3-none-any.whl from Kinova and run "
            "'pip install --no-deps kortex_api-2.6.0.post3-py3-none-any.whl "
            '"protobuf==3.20.*"\' (or use KortexArm.emulated() without an arm)'
        ) from exc
    return SimpleNamespace(
        TCPTransport=TCPTransport,
        UDPTransport=UDPTransport,
        RouterClient=RouterClient,
        RouterClientSendOptions=RouterClientSendOptions,
        SessionManager=SessionManager,
        BaseClient=BaseClient,
        BaseCyclicClient=BaseCyclicClient,
        ActuatorConfigClient=ActuatorConfigClient,
        KServerException=KServerException,
        Session_pb2=Session_pb2,
        Base_pb2=Base_pb2,
        BaseCyclic_pb2=BaseCyclic_pb2,
        ActuatorConfig_pb2=ActuatorConfig_pb2,
    )


def _wrap_rad(deg: np.ndarray) -> np.ndarray:
    """Kortex degrees (any range, usually [0, 360)) to rad in (-pi, pi]."""
    return np.deg2rad((np.asarray(deg) + 180.0) % 360.0 - 180.0)


class KortexArm(Arm):
    """The ``Arm`` interface on a Gen3 Lite through Kortex low-level servoing at 1 kHz.

    Args:
        ip: the arm's address. username, password: its credentials.
        robot: the nominal model (limits, named poses), default "gen3_lite".
        api: the kortex_api namespace (default: ``import_kortex_api()``; an emulator's
            ``api`` for tests).
        clock, sleep: time source (s) and sleep function; ``pace`` waits for the next 1 ms
            tick before each send.
        max_cycle_gap: s between two cycles beyond which the session fails (missed cycle).
        stale_after: s without a new feedback frame beyond which the session fails.
    """

    def __init__(
        self,
        ip: str = "192.168.1.10",
        username: str = "admin",
        password: str = "admin",
        *,
        robot: str | Robot = "gen3_lite",
        api: SimpleNamespace | None = None,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
        pace: bool = True,
        max_cycle_gap: float = 0.003,
        stale_after: float = 0.010,
        limits: ArmLimits | None = None,
    ):
        self.robot = load_robot(robot)
        if self.robot.nv != len(DEVICE_IDS):
            raise HardwareFault(
                f"the Gen3 Lite has 6 actuators; {self.robot.name} has {self.robot.nv}"
            )
        super().__init__(
            self.robot.joint_names,
            limits or ArmLimits.from_robot(self.robot),
            self.robot.named_poses,
        )
        self.api = api if api is not None else import_kortex_api()
        self.ip, self._credentials = ip, (username, password)
        self._clock, self._sleep, self._pace = clock, sleep, pace
        self.max_cycle_gap, self.stale_after = float(max_cycle_gap), float(stale_after)
        self._session = self._session_rt = None
        self._tcp = self._udp = None
        self._low_level = False
        self._last_send: float | None = None
        self._last_fresh = 0.0
        self._last_frame: int | None = None
        self.max_jitter_us = 0
        self.cycles = 0
        self._t0 = 0.0
        try:
            self._open()
        except BaseException:
            self._closed = True
            self._shutdown()
            raise

    @classmethod
    def emulated(cls, emulator=None, **kwargs) -> KortexArm:
        """An adapter on a ``KortexEmulator`` (lock step: the emulator's clock, no sleeping)."""
        if emulator is None:
            from jaxcomp.hardware.kortex_emulator import KortexEmulator

            emulator = KortexEmulator()
        kwargs.setdefault("clock", emulator.clock)
        kwargs.setdefault("sleep", lambda s: None)
        arm = cls(api=emulator.api, **kwargs)
        arm.emulator = emulator
        return arm

    # ----------------------------------------------------------------- session
    def _open(self) -> None:
        api = self.api
        self._tcp = api.TCPTransport()
        router = api.RouterClient(self._tcp, self._router_error)
        self._tcp.connect(self.ip, TCP_PORT)
        self._udp = api.UDPTransport()
        router_rt = api.RouterClient(self._udp, self._router_error)
        self._udp.connect(self.ip, UDP_PORT)
        self._routers = (router, router_rt)
        info = api.Session_pb2.CreateSessionInfo()
        info.username, info.password = self._credentials
        info.session_inactivity_timeout = 60000  # ms
        info.connection_inactivity_timeout = 2000  # ms
        self._session = api.SessionManager(router)
        self._session.CreateSession(info)
        self._session_rt = api.SessionManager(router_rt)
        self._session_rt.CreateSession(info)
        self._base = api.BaseClient(router)
        self._cyclic = api.BaseCyclicClient(router_rt)
        self._config = api.ActuatorConfigClient(router)
        self._options = api.RouterClientSendOptions()
        self._options.andForget = False
        self._options.delay_before_timeout = 0
        self._options.timeout_ms = 3

        fb = self._cyclic.RefreshFeedback()
        if len(fb.actuators) != len(DEVICE_IDS):
            raise HardwareFault(f"expected 6 actuators, the arm reports {len(fb.actuators)}")
        faults = self._fault_bits(fb)
        if faults:
            raise HardwareFault("the arm is in fault: " + "; ".join(faults), faults)
        mode = api.Base_pb2.ServoingModeInformation()
        mode.servoing_mode = api.Base_pb2.ServoingMode.Value("LOW_LEVEL_SERVOING")
        self._base.SetServoingMode(mode)
        self._low_level = True
        fb = self._cyclic.RefreshFeedback()
        self._command = api.BaseCyclic_pb2.Command()
        for a in fb.actuators:
            c = self._command.actuators.add()
            c.flags = 1  # servoing
            c.position = a.position
        self._command.frame_id = fb.frame_id
        self._fb = fb
        self._send_modes(dict.fromkeys(range(self.n), ControlMode.POSITION))
        t = self._clock()
        self._t0 = t
        self._last_fresh = t
        self._start(self._state_from(fb, t, ()))

    def _router_error(self, exc) -> None:
        log.error("Kortex router error: %s", exc)

    def _send_modes(self, changes: dict[int, ControlMode]) -> None:
        api = self.api
        for j, mode in changes.items():
            info = api.ActuatorConfig_pb2.ControlModeInformation()
            info.control_mode = api.ActuatorConfig_pb2.ControlMode.Value(_MODE_NAME[mode])
            self._config.SetControlMode(info, DEVICE_IDS[j])

    # ----------------------------------------------------------------- Arm hooks
    def _switch(self, changes: dict[int, ControlMode]) -> None:
        self._send_modes(changes)
        self._last_send = None  # a configuration call may take ms: no missed-cycle test next

    def _exchange(self, modes, position, velocity, current) -> ArmState:
        now = self._clock()
        if self._pace and self._last_send is not None:
            wait = self._last_send + self.dt - now
            if wait > 0:
                self._sleep(wait)
                now = self._clock()
        faults: list[str] = []
        if self._last_send is not None and now - self._last_send > self.max_cycle_gap:
            faults.append(
                f"missed cycle: {1e3 * (now - self._last_send):.1f} ms since the last one "
                f"(limit {1e3 * self.max_cycle_gap:.1f} ms)"
            )
        self._last_send = now
        cmd, fb = self._command, self._fb
        cmd.frame_id = (cmd.frame_id + 1) % 65536
        pos_deg = np.rad2deg(position) % 360.0
        vel_deg = np.rad2deg(velocity)
        for i, a in enumerate(cmd.actuators):
            a.command_id = cmd.frame_id
            measured = fb.actuators[i]
            mode = modes[i]
            if mode is ControlMode.POSITION:
                a.position = pos_deg[i]
                a.velocity = 0.0
                a.current_motor = measured.current_motor
            else:  # echo the measured position: no following error
                a.position = measured.position
                if mode is ControlMode.VELOCITY:
                    a.velocity = vel_deg[i]
                    a.current_motor = measured.current_motor
                else:
                    a.velocity = 0.0
                    a.current_motor = current[i]
        try:
            new = self._cyclic.Refresh(cmd, 0, self._options)
        except self.api.KServerException as exc:
            faults.append(f"the arm rejected the cyclic command: {exc}")
            new = fb
        t = self._clock()
        if new is not fb and new.frame_id != self._last_frame:
            self._last_fresh = t
            self._fb = fb = new
        elif t - self._last_fresh > self.stale_after:
            faults.append(
                f"stale feedback: no new frame for {1e3 * (t - self._last_fresh):.1f} ms "
                f"(limit {1e3 * self.stale_after:.1f} ms)"
            )
        self._last_frame = fb.frame_id
        self.cycles += 1
        return self._state_from(fb, t, faults + self._fault_bits(fb))

    def _fault_bits(self, fb) -> list[str]:
        out = []
        for i, a in enumerate(fb.actuators):
            if a.fault_bank_a or a.fault_bank_b:
                out.append(
                    f"actuator {DEVICE_IDS[i]} ({self.joint_names[i]}): fault bank A "
                    f"{a.fault_bank_a:#x}, bank B {a.fault_bank_b:#x}"
                )
        return out

    def _state_from(self, fb, t: float, faults) -> ArmState:
        acts = fb.actuators
        jitter = max(a.jitter_comm for a in acts)
        self.max_jitter_us = max(self.max_jitter_us, jitter)
        return ArmState(
            t - self._t0,
            _wrap_rad([a.position for a in acts]),
            np.deg2rad([a.velocity for a in acts]),
            np.array([a.current_motor for a in acts]),
            tuple(faults),
            self._modes_tuple,
            float(jitter),
        )

    def _after_fault(self, state: ArmState) -> None:
        self.close()

    def _clear_faults(self) -> None:
        self._base.ClearFaults()

    def _shutdown(self) -> None:
        """Every actuator to POSITION, SINGLE_LEVEL_SERVOING, sessions closed: each step is
        tried even when an earlier one fails (or is interrupted); the first error is re-raised."""
        errors: list[BaseException] = []

        def attempt(step: Callable[[], None]) -> None:
            try:
                step()
            except BaseException as exc:  # noqa: BLE001 - Ctrl-C must not skip the rest
                errors.append(exc)
                log.error("Kortex shutdown step failed: %r", exc)

        if self._low_level:
            attempt(self._hold_cycle)
            attempt(lambda: self._send_modes(dict.fromkeys(range(self.n), ControlMode.POSITION)))
            attempt(self._single_level)
        for session in (self._session, self._session_rt):
            if session is not None:
                attempt(session.CloseSession)
        for router in getattr(self, "_routers", ()):
            attempt(lambda r=router: r.SetActivationStatus(False))
        for transport in (self._tcp, self._udp):
            if transport is not None:
                attempt(transport.disconnect)
        self._session = self._session_rt = None
        if errors and not isinstance(errors[0], self.api.KServerException):
            raise errors[0]

    def _hold_cycle(self) -> None:
        """One frame that echoes the measured positions, so POSITION mode holds in place."""
        cmd, fb = self._command, self._fb
        cmd.frame_id = (cmd.frame_id + 1) % 65536
        for i, a in enumerate(cmd.actuators):
            a.command_id = cmd.frame_id
            a.position = fb.actuators[i].position
            a.velocity = 0.0
            a.current_motor = fb.actuators[i].current_motor
        self._fb = self._cyclic.Refresh(cmd, 0, self._options)

    def _single_level(self) -> None:
        mode = self.api.Base_pb2.ServoingModeInformation()
        mode.servoing_mode = self.api.Base_pb2.ServoingMode.Value("SINGLE_LEVEL_SERVOING")
        self._base.SetServoingMode(mode)
        self._low_level = False


__all__ = ["DEVICE_IDS", "KortexArm", "import_kortex_api"]
