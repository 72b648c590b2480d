"""The real Clearpath Dingo-O: ``geometry_msgs/Twist`` on ``cmd_vel`` through ROS 2.

``DingoBase`` is the ``Base`` interface. Commands pass the same ``TwistLimits`` and
``TwistLimiter`` as the simulated base (velocity and acceleration limits, stop after 0.25 s
without a command); ``update()`` publishes the limited twist and runs ``rate_hz`` times a
second on a background thread when ROS is used. Odometry comes from ``nav_msgs/Odometry`` on
``odom``. ``rclpy`` is imported only when no ``publish`` function is given, so the logic runs
and is tested without ROS: pass ``publish`` (called with a (3,) twist) and a ``clock``, call
``update()`` yourself and feed ``on_odometry``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from jaxcomp.hardware.interface import Base, BaseState
from jaxcomp.hardware.mecanum import MecanumGeometry, TwistLimiter, TwistLimits

log = logging.getLogger(__name__)


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The yaw of an orientation.

    Args:
        x, y, z, w: a unit quaternion, in ROS order.

    Returns:
        rad, the rotation about z, in [-pi, pi].
    """
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class _RosLink:
    """rclpy node with a Twist publisher and an Odometry subscription, spun on a thread."""

    def __init__(self, base: DingoBase, topic: str, odom_topic: str, node_name: str):
        try:
            import rclpy
            from geometry_msgs.msg import Twist
            from nav_msgs.msg import Odometry
            from rclpy.executors import SingleThreadedExecutor
        except ImportError as exc:
            raise ImportError(
                "the Dingo adapter needs ROS 2 (rclpy, geometry_msgs, nav_msgs): source your "
                "ROS 2 installation, or pass publish= to run without ROS"
            ) from exc
        self._rclpy, self._twist = rclpy, Twist
        if not rclpy.ok():
            rclpy.init()
        self.node = rclpy.create_node(node_name)
        self.pub = self.node.create_publisher(Twist, topic, 10)
        self.node.create_subscription(Odometry, odom_topic, self._on_odom, 10)
        self._base = base
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def publish(self, twist: np.ndarray) -> None:
        msg = self._twist()
        msg.linear.x, msg.linear.y, msg.angular.z = (float(v) for v in twist)
        self.pub.publish(msg)

    def _on_odom(self, msg) -> None:
        p, o, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        self._base.on_odometry(
            stamp,
            (p.x, p.y, yaw_from_quaternion(o.x, o.y, o.z, o.w)),
            (v.linear.x, v.linear.y, v.angular.z),
        )

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


class DingoBase(Base):
    """``Base`` on the real Dingo-O (see the module docstring).

    Args:
        publish: function taking the (3,) twist to send; default: ROS 2 ``cmd_vel``.
        clock: monotonic time source, s.
        limits: default ``TwistLimits()`` (Clearpath's figures).
        rate_hz: publishing rate of the background loop (ROS only).
        topic, odom_topic, node_name: ROS names.
    """

    def __init__(
        self,
        publish: Callable[[np.ndarray], None] | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        limits: TwistLimits | None = None,
        rate_hz: float = 50.0,
        topic: str = "cmd_vel",
        odom_topic: str = "odom",
        node_name: str = "jaxcomp_dingo",
    ):
        super().__init__(limits or TwistLimits())
        self.geometry = MecanumGeometry()
        self._clock = clock
        self._limiter = TwistLimiter(self.limits)
        self._lock = threading.Lock()
        self._odom = BaseState(0.0, np.zeros(3), np.zeros(3))
        self._ros = None
        self._stop_event = threading.Event()
        self._thread = None
        if publish is None:
            self._ros = _RosLink(self, topic, odom_topic, node_name)
            publish = self._ros.publish
            self._thread = threading.Thread(target=self._loop, args=(1.0 / rate_hz,), daemon=True)
        self._publish = publish
        if self._thread is not None:
            self._thread.start()

    def _loop(self, period: float) -> None:
        while not self._stop_event.wait(period):
            try:
                self.update()
            except Exception:  # keep publishing; a ROS hiccup must not stop the loop
                log.exception("Dingo publish failed")

    def _send(self, twist: np.ndarray) -> None:
        with self._lock:
            self._limiter.command(twist, self._clock())

    def stop(self) -> None:
        with self._lock:
            self._limiter.stop()

    def update(self) -> np.ndarray:
        """Publish the limited twist for now (called by the loop, or by the user) and return it."""
        with self._lock:
            twist = self._limiter.update(self._clock()).copy()
        self._publish(twist)
        return twist

    def on_odometry(self, t: float, pose, twist) -> None:
        """Record odometry (the ROS subscription's callback, or the user's without ROS).

        Args:
            t: s, the message's stamp.
            pose: (3,) x m, y m, yaw rad in the odometry frame.
            twist: (3,) vx m/s, vy m/s, wz rad/s in the base frame.
        """
        self._odom = BaseState(float(t), np.asarray(pose, float), np.asarray(twist, float))

    def odometry(self) -> BaseState:
        return self._odom

    def _shutdown(self) -> None:
        self._stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        try:
            self._publish(np.zeros(3))  # the Dingo's controller ramps down within its limits
        finally:
            if self._ros is not None:
                self._ros.close()
