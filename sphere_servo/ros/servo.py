"""
``servo``: features → camera twist, ``v_c = −λ L̂⁺ (s − s*)`` (paper eq. 17).

Subscribes
    ``features/<feature_set>``          sensor_msgs/JointState  s (``position``)
    ``features/<feature_set>/desired``  sensor_msgs/JointState  s* (``position``);
                                        transient-local, so the desired published before
                                        the servo started reaches it
Publishes
    ``camera/cmd_vel``  geometry_msgs/TwistStamped  (v, ω) in the camera optical frame;
                        header = the answered image's header; a zero stamp (and the last
                        image's frame) when it answers no image: the watchdog's zero twists
                        and the last word
    ``~/state``         diagnostic_msgs/DiagnosticArray  one status per twist, same header:
                        message one of ``waiting | disabled | no desired | servoing |
                        converged | target lost | stale``; values: reason, error_norm,
                        converged, target_lost, gain, saturated, image_age (s: the node
                        clock at the twist's publication − the image stamp), iteration,
                        stamp, desired_stamp (of the image the desired held came from)
    ``/diagnostics``    diagnostic_msgs/DiagnosticArray  the same status, on change and at
                        1 Hz (:mod:`sphere_servo.ros.diagnostics`)
    ``~/enabled``       std_msgs/Bool  whether the servo is enabled; reliable,
                        transient-local, depth 1, published on every change and ``false`` as
                        the last word: arm_sim refuses its jumps while it is ``true``

Services
    ``~/enable``        std_srvs/SetBool  start/stop servoing (with ``start_enabled: false``
                        the servo sends zero twists until enabled: the launcher teaches the
                        desired image meanwhile)

What the servo decides (each image answered once, ``max_image_age``, the stamp rule, the
physical bounds of s and s*, the watchdog, the zero twists, no twist before a desired, the
desired dropped when its publisher is gone) is
:class:`~sphere_servo.pipeline.servo.ServoCore`'s; on shutdown the last word is a zero
twist. ``feature_set`` ∈ {s_n, s}: their interaction matrices depend on s only (eqs. 6 and
16). The desired topic's publishers are looked up every ``DESIRED_CHECK`` s: a features
node that stopped is seen at once, one killed with SIGKILL after its participant's lease
(``config/fastdds.xml``: 10 s; Fast DDS's default: 20 s).
"""
from __future__ import annotations

import time

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TwistStamped
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from sphere_servo.core.measurement import MeasurementError
from sphere_servo.pipeline.common import stamp_ns, stamp_text
from sphere_servo.pipeline.params import ServoParams
from sphere_servo.pipeline.servo import Ignored, ServoCommand, ServoCore, Unanswered
from sphere_servo.ros.conversions import twist_from_array
from sphere_servo.ros.diagnostics import StatusPublisher
from sphere_servo.ros.guard import guarded, guarded_service
from sphere_servo.ros.logs import ThrottledLog
from sphere_servo.ros.params import declare_all, run
from sphere_servo.ros.qos import PIPELINE, writer
from sphere_servo.ros.vectors import (desired_from_msg, DESIRED_QOS, desired_topic,
                                      ENABLED_QOS, features_from_msg)
from sphere_servo.sim.arm import CAMERA_FRAME
from std_msgs.msg import Bool, Header
from std_srvs.srv import SetBool

HARDWARE_ID = 'camera'  # the eye-in-hand camera whose twist the servo commands
WATCHDOG_PERIOD = 0.05  # s, wall clock
DESIRED_CHECK = 0.5     # s between two looks at the desired topic's publishers


class ServoNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('servo', **kwargs)
        self.core = ServoCore(declare_all(self, ServoParams))
        fset = self.core.feature_set
        self.frame_id = CAMERA_FRAME  # of the last image answered
        self.pub_twist = self.create_publisher(TwistStamped, 'camera/cmd_vel',
                                               writer('camera/cmd_vel'))
        self.status = StatusPublisher(self, HARDWARE_ID, self.core.on_tick(0.0).status())
        self.log = ThrottledLog(self.get_logger(), period=2.0)
        # every frame gets its answer (a 60 Hz camera loses none); which frames are usable
        # is the core's decision: see max_image_age
        self.create_subscription(JointState, f'features/{fset}', self._on_features, PIPELINE)
        sub = self.create_subscription(JointState, desired_topic(fset), self._on_desired,
                                       DESIRED_QOS)
        self.desired_topic = sub.topic_name
        self.pub_enabled = self.create_publisher(Bool, '~/enabled', ENABLED_QOS)
        self.pub_enabled.publish(Bool(data=self.core.enabled))
        self.create_service(SetBool, '~/enable', self._srv_enable)
        # wall (steady) clock: in lockstep, sim time freezes exactly when the pipeline dies
        self.create_timer(WATCHDOG_PERIOD, self._watchdog,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.create_timer(DESIRED_CHECK, self._check_desired,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'servoing on {fset}; no twist before the desired features '
                               f'arrive on {sub.topic_name}')

    @guarded_service
    def _srv_enable(self, request, response):
        self.core.enable(request.data)
        self.pub_enabled.publish(Bool(data=self.core.enabled))  # before the reply
        response.success = True
        response.message = 'servo enabled' if self.core.enabled else 'servo disabled'
        self.get_logger().info(response.message)
        return response

    def _desired_publishers(self) -> frozenset:
        return frozenset(bytes(e.endpoint_gid)
                         for e in self.get_publishers_info_by_topic(self.desired_topic))

    @guarded
    def _check_desired(self) -> None:
        if self.core.on_desired_publishers(self._desired_publishers()):
            self.get_logger().warn(f'{self.desired_topic} lost its publisher (the features '
                                   'node is gone): desired features dropped, teach again')

    @guarded
    def _on_desired(self, msg: JointState) -> None:
        st = msg.header.stamp
        try:
            refused = self.core.set_desired(desired_from_msg(msg, self.core.feature_set),
                                            stamp_ns(st.sec, st.nanosec),
                                            self._desired_publishers())
            reason = '' if refused is None else refused.reason
        except MeasurementError as exc:
            reason = str(exc)
        if reason:
            self.log.error(f'desired features refused, the servo keeps the ones it had: '
                           f'{reason}')
            return
        self.get_logger().info(f'desired features of the image stamped '
                               f'{stamp_text(self.core.desired_stamp_ns)}: '
                               f's* = {np.round(self.core.s_star, 4).tolist()}')

    @guarded
    def _on_features(self, msg: JointState) -> None:
        s = None
        try:
            s, invalid = features_from_msg(msg, self.core.feature_set), ''
        except MeasurementError as exc:
            invalid = str(exc)
        st = msg.header.stamp
        out = self.core.on_features(stamp_ns(st.sec, st.nanosec), s,
                                    self.get_clock().now().nanoseconds, time.monotonic(),
                                    invalid)
        if isinstance(out, Unanswered):
            if out.why is Ignored.TOO_OLD:
                self.log.info(f'skipping features of an image {out.age_ns * 1e-9:.3f} s old '
                              f'(max_image_age {self.core.max_age_ns * 1e-9:g} s; '
                              f'{out.skipped} so far)')
            return
        self.frame_id = msg.header.frame_id or self.frame_id
        # a refused stamp is answered with a zero twist that answers no image
        self._send(out, msg.header if out.stamp_ns is not None else None)

    @guarded
    def _watchdog(self) -> None:
        cmd = self.core.on_tick(time.monotonic())
        if cmd is not None:
            self._send(cmd)

    def _unstamped(self) -> Header:
        """Return the header of a twist that answers no image: zero stamp, the camera frame."""
        return Header(stamp=Time(), frame_id=self.frame_id)

    def _send(self, cmd: ServoCommand, header: Header | None = None) -> None:
        """Publish the twist (with the answered image's header), then the state."""
        if cmd.fault:
            self.log.error(f'no valid twist: {cmd.fault}')
        hdr = header if header is not None else self._unstamped()
        if cmd.send_twist:
            self.pub_twist.publish(TwistStamped(header=hdr, twist=twist_from_array(cmd.twist)))
        age_ns = None
        if header is not None:
            age_ns = self.get_clock().now().nanoseconds - cmd.stamp_ns
        if cmd.changed:
            self.get_logger().info(f'state: {cmd.state.value}' + (
                f' ({cmd.reason})' if cmd.reason else ''))
        self.status.update(cmd.status(age_ns), hdr)

    def go_safe(self, *_) -> None:
        """Send a zero twist (the guard's answer to a callback that failed)."""
        self.pub_twist.publish(TwistStamped(header=self._unstamped(),
                                            twist=twist_from_array(np.zeros(6))))

    def on_shutdown(self) -> None:
        """Last word: a zero twist, and no longer enabled."""
        self.go_safe()
        self.pub_enabled.publish(Bool(data=False))


def main(args=None):
    run(ServoNode, 'servo', args)


if __name__ == '__main__':
    main()
