"""``servo``: features → camera twist, ``v_c = −λ L̂⁺ (s − s*)`` (paper eq. 17).

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

Each image is answered once: a repeat of the last image's features is ignored, and so are
features whose image is older than ``max_image_age`` on the node's clock (sim time with
``use_sim_time``). In lockstep ``max_image_age: 0`` answers only the current frame: each
command steps the simulator, so answering a superseded frame (a backlog that Fast DDS
delivers late, in a burst, under load) would leave several frames in flight and the servo
acting on old images, and the run would depend on the machine's load.

Safety: a zero twist is sent while disabled, when the target or a mark is lost (empty
features), when no usable features have come for ``timeout`` wall seconds (a dead detector,
or only late images, stop the arm even when simulated time is frozen), when the law cannot
give a finite twist, and on shutdown.

``feature_set`` ∈ {s_n, s}: their interaction matrices depend on s only (eqs. 6 and 16).
"""
from __future__ import annotations

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist, TwistStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import SetBool

from sphere_servo.core.control import (INTERACTION_CHOICES, AdaptiveGain, VectorController)
from sphere_servo.core.geometry import GeometryError
from sphere_servo.ros.conversions import twist_from_array
from sphere_servo.ros.params import Param, declare_all, run
from sphere_servo.ros.vectors import features_from_msg

INF = float('inf')
PARAMS = {
    'feature_set': Param('s_n', 'feature set to servo on', choices=('s_n', 's'),
                         read_only=True),
    'r_hat': Param(0.05, 'estimated sphere radius r̂ (m); any r̂ > 0 is stable (paper §III)',
                   range=(1e-6, 1e3), read_only=True),
    'gain': Param(0.5, 'constant gain λ (1/s), when adaptive is false', range=(1e-6, 1e3),
                  read_only=True),
    'adaptive': Param(False, "adaptive gain (ViSP's vpAdaptiveGain on ‖s − s*‖∞)",
                      read_only=True),
    'lambda_0': Param(2.0, 'adaptive gain at zero error (1/s)', range=(1e-6, 1e3),
                      read_only=True),
    'lambda_inf': Param(0.3, 'adaptive gain at infinite error (1/s)', range=(1e-6, 1e3),
                        read_only=True),
    'slope_0': Param(10.0, 'adaptive gain slope at zero error', range=(1e-6, 1e6),
                     read_only=True),
    'interaction': Param('current', 'where L̂ is evaluated', choices=INTERACTION_CHOICES,
                         read_only=True),
    'v_max': Param(0.2, 'translational speed limit (m/s); the twist is scaled as a whole',
                   range=(1e-6, 10.0), read_only=True),
    'w_max': Param(1.0, 'rotational speed limit (rad/s)', range=(1e-6, 100.0),
                   read_only=True),
    'tol': Param(1e-3, 'converged when ‖s − s*‖₂ < tol', range=(1e-12, 10.0), read_only=True),
    'timeout': Param(0.5, 'zero twists when no usable features came for this long (wall s)',
                     range=(0.01, 60.0), read_only=True),
    'max_image_age': Param(0.5, "skip features whose image is older than this on the node's "
                           'clock (s); 0: only the current frame (lockstep)', range=(0.0, 60.0),
                           read_only=True),
    'start_enabled': Param(True, 'servo at once; false: send zero twists until ~/enable',
                           read_only=True),
}


class ServoNode(Node):
    """See the module docstring."""

    def __init__(self):
        super().__init__('servo')
        p = declare_all(self, PARAMS)
        gain = AdaptiveGain(p['lambda_0'], p['lambda_inf'], p['slope_0']) \
            if p['adaptive'] else p['gain']
        self.law = VectorController(p['feature_set'], p['r_hat'], gain=gain,
                                    interaction=p['interaction'], v_max=p['v_max'],
                                    w_max=p['w_max'], tol=p['tol'])
        self.feature_set, self.timeout = p['feature_set'], p['timeout']
        self.max_age_ns = int(round(p['max_image_age'] * 1e9))
        self.skipped = 0  # features skipped as older than max_image_age
        self.pub_twist = self.create_publisher(Twist, 'camera/cmd_vel', 100)
        self.pub_stamped = self.create_publisher(TwistStamped, 'camera/cmd_vel_stamped', 100)
        self.pub_state = self.create_publisher(DiagnosticStatus, 'servo/state', 100)
        # every frame gets its answer (a 60 Hz camera loses none); which frames are usable
        # is _on_features' decision: see max_image_age
        self.create_subscription(JointState, f'features/{self.feature_set}', self._on_features,
                                 10)
        self.last_stamp = None  # image stamp of the last features answered
        self.enabled = p['start_enabled']
        self.create_service(SetBool, '~/enable', self._srv_enable)
        self.last_rx = None  # wall time of the last features
        self.iteration = 0
        self.state = 'waiting'
        # wall (steady) clock: in lockstep, sim time freezes exactly when the pipeline dies
        self.create_timer(0.05, self._watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # --- outputs ---------------------------------------------------------------------------
    def _send(self, v_c: np.ndarray, header=None) -> None:
        tw = twist_from_array(v_c)
        self.pub_twist.publish(tw)
        if header is not None:
            self.pub_stamped.publish(TwistStamped(header=header, twist=tw))

    def _publish_state(self, state: str, level: int, stamp=None, **values) -> None:
        if state != self.state:
            self.get_logger().info(f'state: {state}' + (
                f" ({values['reason']})" if values.get('reason') else ''))
        self.state = state
        vals = dict(values, iteration=self.iteration)
        if stamp is not None:
            vals['stamp'] = f'{stamp.sec}.{stamp.nanosec:09d}'
        self.pub_state.publish(DiagnosticStatus(
            level=level, name='servo', message=state,
            values=[KeyValue(key=k, value=str(v)) for k, v in vals.items()]))

    def _stop(self, state: str, reason: str, header=None) -> None:
        self._send(np.zeros(6), header)
        self._publish_state(state, DiagnosticStatus.WARN,
                            header.stamp if header is not None else None,
                            reason=reason, converged=False, target_lost=True)

    # --- inputs ----------------------------------------------------------------------------
    def _srv_enable(self, request, response):
        self.enabled = bool(request.data)
        response.success = True
        response.message = 'servo enabled' if self.enabled else 'servo disabled'
        self.get_logger().info(response.message)
        return response

    def _on_features(self, msg: JointState) -> None:
        stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if stamp == self.last_stamp:  # the same image again (a re-publication): answered
            return
        age_ns = self._age_ns(msg.header.stamp)
        if age_ns > self.max_age_ns:  # superseded or late: not usable, not answered
            self.skipped += 1
            self.get_logger().info(
                f'skipping features of an image {age_ns * 1e-9:.3f} s old (max_image_age '
                f'{self.max_age_ns * 1e-9:g} s; {self.skipped} so far)',
                throttle_duration_sec=2.0)
            return
        self.last_rx = time.monotonic()
        self.last_stamp = stamp
        if not self.enabled:
            self._send(np.zeros(6), msg.header)
            return self._publish_state('disabled', DiagnosticStatus.OK, msg.header.stamp,
                                       converged=False, target_lost=False)
        self.iteration += 1
        try:
            fs = features_from_msg(msg, self.feature_set)
            if fs is None:
                return self._stop('target lost', 'the target or a mark is lost', msg.header)
            out = self.law.compute(*fs)
        except GeometryError as exc:  # MeasurementError, ControlError
            self.get_logger().error(f'no valid twist: {exc}', throttle_duration_sec=2.0)
            return self._stop('target lost', str(exc), msg.header)
        v_c = np.zeros(6) if out.converged else out.v_c
        self._send(v_c, msg.header)
        self._publish_state('converged' if out.converged else 'servoing', DiagnosticStatus.OK,
                            msg.header.stamp, error_norm=f'{out.error_norm:.6g}',
                            converged=out.converged, target_lost=False,
                            gain=f'{out.gain:.4g}', saturated=out.saturated,
                            image_age=f'{self._age_ns(msg.header.stamp) * 1e-9:.6f}')

    def _age_ns(self, stamp) -> int:
        """Nanoseconds from the image stamp to now on the node's clock (negative if the
        clock is behind, e.g. no /clock yet with use_sim_time)."""
        return self.get_clock().now().nanoseconds - (stamp.sec * 1_000_000_000 + stamp.nanosec)

    def _watchdog(self) -> None:
        if self.last_rx is None:
            self._send(np.zeros(6))
            self._publish_state('waiting', DiagnosticStatus.OK, reason='no features yet',
                                converged=False, target_lost=False)
        elif time.monotonic() - self.last_rx > self.timeout:
            self._stop('stale', f'no usable features for more than {self.timeout} s')

    def on_shutdown(self) -> None:
        """Last word: a zero twist."""
        self._send(np.zeros(6))


def main(args=None):
    run(ServoNode, 'servo', args)


if __name__ == '__main__':
    main()
