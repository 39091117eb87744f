"""
A node's status on its private ``~/state`` topic and on ``/diagnostics``.

Both carry ``diagnostic_msgs/DiagnosticArray`` with one ``DiagnosticStatus`` of the node:
``name`` ``<node>: state``, ``hardware_id``, ``level`` (OK/WARN/ERROR), ``message`` the value
of the node's state enum, ``values`` the core's named values (key → text):

- ``~/state`` (``/servo/state``, ``/arm_sim/state``, …): every update, machine-readable, with
  the header of the input it answers (the image's: stamp and frame; a zero stamp when it
  answers none, e.g. the servo's watchdog); reliable, volatile, depth 100.
- ``/diagnostics``: for rqt_robot_monitor, Foxglove's diagnostics panel or a
  ``diagnostic_aggregator``, the latest status when its level or message changes and once a
  second (wall clock), stamped with the node's clock; reliable, volatile, depth 10.
"""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from sphere_servo.pipeline.common import NodeStatus
from sphere_servo.ros.qos import DIAGNOSTICS, writer
from std_msgs.msg import Header

DIAGNOSTICS_PERIOD = 1.0  # s, wall clock


def diagnostic_status(status: NodeStatus, name: str, hardware_id: str) -> DiagnosticStatus:
    """Build the ``DiagnosticStatus`` of a node's status."""
    return DiagnosticStatus(level=bytes([status.level]), name=name, message=status.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in status.values.items()])


def state_of(msg) -> tuple[str, dict[str, str]] | None:
    """Return (message, values) of a ``~/state`` message (rclpy or rosbags); None if empty."""
    if not len(msg.status):
        return None
    st = msg.status[0]
    return st.message, {kv.key: kv.value for kv in st.values}


class StatusPublisher:
    """Publishes a node's status on ``~/state`` and ``/diagnostics`` (module docstring)."""

    def __init__(self, node, hardware_id: str, status: NodeStatus):
        self.node = node
        self.name = f'{node.get_name()}: state'
        self.hardware_id = hardware_id
        self.pub_state = node.create_publisher(DiagnosticArray, '~/state',
                                               writer('<node>/state'))
        self.pub_diagnostics = node.create_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS)
        self.status = status
        self._sent: tuple | None = None  # (level, message) last on /diagnostics
        node.create_timer(DIAGNOSTICS_PERIOD, self.publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.publish_diagnostics()

    def state_msg(self, status: NodeStatus, header: Header) -> DiagnosticArray:
        """Return the ``~/state`` message of ``status`` with ``header``."""
        return DiagnosticArray(header=header,
                               status=[diagnostic_status(status, self.name, self.hardware_id)])

    def update(self, status: NodeStatus, header: Header) -> None:
        """Publish ``status`` on ``~/state`` with ``header``, then :meth:`note` it."""
        self.pub_state.publish(self.state_msg(status, header))
        self.note(status)

    def note(self, status: NodeStatus) -> None:
        """Make ``status`` the latest; publish it on /diagnostics if level or message changed."""
        self.status = status
        if (status.level, status.message) != self._sent:
            self.publish_diagnostics()

    def publish_diagnostics(self) -> None:
        """Publish the latest status on ``/diagnostics``, stamped with the node's clock."""
        st = self.status
        self._sent = (st.level, st.message)
        self.pub_diagnostics.publish(self.state_msg(
            st, Header(stamp=self.node.get_clock().now().to_msg())))
