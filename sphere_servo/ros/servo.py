"""
``servo``: features → camera twist, ``v_c = −λ L̂⁺ (s − s*)`` (paper eq. 17).

Subscribes
    ``features/<feature_set>``  sensor_msgs/JointState  s (position), s* (velocity)
Publishes
    ``camera/cmd_vel``          geometry_msgs/Twist         (v, ω) in the camera optical frame
    ``camera/cmd_vel_stamped``  geometry_msgs/TwistStamped  the same, header = the image's
    ``servo/state``             diagnostic_msgs/DiagnosticStatus  message one of
                                ``waiting | disabled | servoing | converged | target lost |
                                stale``;
                                values: error_norm, converged, target_lost, iteration, gain,
                                saturated, stamp, image_age (s: the node clock at the
                                twist's publication − the image stamp)

Services
    ``~/enable``                std_srvs/SetBool  start/stop servoing (with ``start_enabled:
                                false`` the servo sends zero twists until enabled: the
                                launcher teaches the desired image meanwhile)

What the servo decides (each image answered once, ``max_image_age``, the watchdog, the zero
twists) is :class:`~sphere_servo.pipeline.servo.ServoCore`'s; on shutdown the last word is
a zero twist. ``feature_set`` ∈ {s_n, s}: their interaction matrices depend on s only
(eqs. 6 and 16).
"""
from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist, TwistStamped
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from sphere_servo.core.measurement import MeasurementError
from sphere_servo.pipeline.common import stamp_ns
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.servo import Ignored, ServoCommand, ServoCore, Unanswered
from sphere_servo.ros.conversions import twist_from_array
from sphere_servo.ros.params import declare_all, run
from sphere_servo.ros.vectors import features_from_msg
from std_srvs.srv import SetBool


class ServoNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('servo', **kwargs)
        self.core = ServoCore(declare_all(self, ServoParams))
        self.pub_twist = self.create_publisher(Twist, 'camera/cmd_vel', 100)
        self.pub_stamped = self.create_publisher(TwistStamped, 'camera/cmd_vel_stamped', 100)
        self.pub_state = self.create_publisher(DiagnosticStatus, 'servo/state', 100)
        # every frame gets its answer (a 60 Hz camera loses none); which frames are usable
        # is the core's decision: see max_image_age
        self.create_subscription(JointState, f'features/{self.core.feature_set}',
                                 self._on_features, 10)
        self.create_service(SetBool, '~/enable', self._srv_enable)
        # wall (steady) clock: in lockstep, sim time freezes exactly when the pipeline dies
        self.create_timer(0.05, self._watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _srv_enable(self, request, response):
        self.core.enable(request.data)
        response.success = True
        response.message = 'servo enabled' if self.core.enabled else 'servo disabled'
        self.get_logger().info(response.message)
        return response

    def _on_features(self, msg: JointState) -> None:
        s = s_star = None
        try:
            fs, invalid = features_from_msg(msg, self.core.feature_set), ''
            if fs is not None:
                s, s_star = fs.s, fs.s_star
        except MeasurementError as exc:
            invalid = str(exc)
        st = msg.header.stamp
        out = self.core.on_features(stamp_ns(st.sec, st.nanosec), s, s_star,
                                    self.get_clock().now().nanoseconds, time.monotonic(),
                                    invalid)
        if isinstance(out, Unanswered):
            if out.why is Ignored.TOO_OLD:
                self.get_logger().info(
                    f'skipping features of an image {out.age_ns * 1e-9:.3f} s old '
                    f'(max_image_age {self.core.max_age_ns * 1e-9:g} s; {out.skipped} so '
                    'far)', throttle_duration_sec=2.0)
            return
        self._send(out, msg.header)

    def _watchdog(self) -> None:
        cmd = self.core.on_tick(time.monotonic())
        if cmd is not None:
            self._send(cmd)

    def _send(self, cmd: ServoCommand, header=None) -> None:
        """Publish the twist (stamped too when it answers an image), then the state."""
        if cmd.fault:
            self.get_logger().error(f'no valid twist: {cmd.fault}', throttle_duration_sec=2.0)
        tw = twist_from_array(cmd.twist)
        self.pub_twist.publish(tw)
        age_ns = None
        if header is not None:
            self.pub_stamped.publish(TwistStamped(header=header, twist=tw))
            age_ns = self.get_clock().now().nanoseconds - cmd.stamp_ns
        if cmd.changed:
            self.get_logger().info(f'state: {cmd.state.value}' + (
                f' ({cmd.reason})' if cmd.reason else ''))
        self.pub_state.publish(DiagnosticStatus(
            level=bytes([cmd.level]), name='servo', message=cmd.state.value,
            values=[KeyValue(key=k, value=v) for k, v in cmd.values(age_ns).items()]))

    def on_shutdown(self) -> None:
        """Last word: a zero twist."""
        self.pub_twist.publish(twist_from_array(np.zeros(6)))


def main(args=None):
    run(ServoNode, 'servo', args)


if __name__ == '__main__':
    main()
