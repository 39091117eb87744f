"""
``arm_sim``: a simulated UR5 with an eye-in-hand camera looking at a marked sphere.

The kinematics, limits and watchdog are :class:`sphere_servo.sim.arm.ArmModel`; images come
from :class:`sphere_servo.vision.renderer.Renderer`. All topic names are relative (remap or
namespace them as usual).

Subscribes
    ``camera/cmd_vel``      geometry_msgs/TwistStamped  camera twist (v, ω) in the *current
                            camera optical frame*, m/s and rad/s: ``header.frame_id`` must be
                            ``camera_optical_frame``. Refused (a warning, throttled; not
                            executed, the arm stopped at once; in lockstep the period passes
                            with the arm held still): another frame, NaN or inf, beyond the
                            arm's physical bound, any while held or in ``error``, and one
                            from a second publisher while another drives (told apart by the
                            message info's publication sequence numbers: one driver at a
                            time); in lockstep, one stamped with another image's time than
                            the last (0 aside: it answers no image), e.g. from before a
                            jump: it steps nothing. Several publishers of the topic are
                            reported (a warning, and the status value
                            ``command_publishers``).
    ``servo/enabled``       std_msgs/Bool  the servo's latched mode: the jumps are refused
                            while it is ``true`` (and its publisher lives)
Publishes (stamps from the simulation clock, which starts at 1.0 s)
    ``camera/image_raw``    sensor_msgs/Image     rgb8, frame_id ``camera_optical_frame``
    ``camera/camera_info``  sensor_msgs/CameraInfo  the true intrinsics, same header
    ``joint_states``        sensor_msgs/JointState  position and the applied velocity
    ``ground_truth/camera_pose``  geometry_msgs/PoseStamped  pose of the camera optical frame
                            in the target frame, ``oMc`` (header.frame_id = ``target_frame``,
                            default ``target``); ``cMo`` is its inverse
    ``~/state``             diagnostic_msgs/DiagnosticArray  per image, its header: level
                            OK/WARN/ERROR, message ``ok|joint_limit|singularity|timeout``,
                            values: ``joints`` (names at a limit), ``sigma_min``, ``scale``,
                            ``sim_time``, ``detail``, then when set ``command_error`` (why
                            the last command was refused), ``step_error``, ``render_error``,
                            ``hold``, ``command_publishers``; message ``error`` (level
                            ERROR) once the state became invalid: commands refused until
                            ``~/reset``
    ``/diagnostics``        diagnostic_msgs/DiagnosticArray  the same status, on change and
                            at 1 Hz (hardware_id ``ur5``)
    ``/clock``              rosgraph_msgs/Clock   the simulation time (both clock modes)
    ``~/markers``           visualization_msgs/MarkerArray  the 3-D scene for RViz and
                            Foxglove, frame ``world`` (no TF needed), stamped as the frame
                            it shows: the UR5's link meshes (MESH_RESOURCE, ``package://
                            example-robot-data/…``; ``markers_mesh_uris: file`` for
                            ``file://`` URIs) at the forward kinematics of ``joint_states``,
                            the target and its marks, the camera frustum, the camera path
                            since the last jump, the desired camera (``desired_cMo``). The
                            whole scene each time (:mod:`sphere_servo.ros.markers`), at the
                            first frame, after a jump and every ``1/markers_rate`` s of sim
                            time (10 Hz; 0: off); reliable, transient-local, depth 1
Services (std_srvs/Trigger; private, e.g. ``/arm_sim/go_desired``)
    ``~/reset``        start configuration, at rest, watchdog re-armed, hold released,
                       error cleared
    ``~/go_start``     jump to the start configuration (IK of ``start_cMo`` when
                       ``start_mode = 'pose'``; parameters are re-read, so set ``start_cMo``
                       then call this to go to a *given* camera pose)
    ``~/go_desired``   jump to the desired configuration (IK of ``desired_cMo``)
    ``~/hold``         drop the current command (the arm stops at once) and latch: every
                       command is refused until ``~/release`` or ``~/reset``
    ``~/release``      release the hold (the next command moves the arm again)
    The three jumps are refused while the servo is enabled (``servo/enabled``): disable it
    first (``/servo/enable false``), as the launcher's teach sequence does.

Clock modes (parameter ``clock_mode``)
    ``realtime``  a wall timer at ``camera_rate`` advances the simulation one period per tick
                  under the last command, then renders and publishes.
    ``lockstep``  each received command advances the simulation exactly one camera period,
                  then renders and publishes exactly one image (a refused command advances
                  the clock with the arm held still, so a loop never stalls). Each image is
                  published at once and *re-published* unchanged (same stamp) when
                  ``idle_republish_period`` wall seconds pass with no command after it (the
                  first one and the one after a jump; any while a servo is enabled), so a
                  subscriber that connects late (or restarts) still gets it. The QoS of each
                  topic is :mod:`sphere_servo.ros.qos`'s (all reliable and volatile).

Poses in parameters are 6 numbers ``[x, y, z, roll, pitch, yaw]`` (metres, radians,
``R = Rz(yaw) Ry(pitch) Rx(roll)``). ``desired_cMo`` / ``start_cMo`` give the target in the
camera frame (``cMo``), ``target_pose`` the target in the robot's ``world`` frame (``wMo``),
``hand_eye`` the camera optical frame in ``tool0`` (``tool0Mc``). The logic (stepping,
jumps, re-publishing) is :class:`~sphere_servo.pipeline.arm_sim.ArmSimCore`'s.
"""
from __future__ import annotations

import functools
import time

from geometry_msgs.msg import PoseStamped, TwistStamped
import numpy as np
from rclpy.clock import Clock as WallClock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from sphere_servo.pipeline.arm_sim import ArmSimCore, SimFrame
from sphere_servo.pipeline.common import stamp_ns
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.ros.conversions import (camera_info_from_intrinsics, image_from_array,
                                          pose_from_se3, stamp_from_ns, twist_to_array)
from sphere_servo.ros.diagnostics import StatusPublisher
from sphere_servo.ros.guard import guarded, guarded_service
from sphere_servo.ros.logs import ThrottledLog
from sphere_servo.ros.markers import marker_array, MARKERS_QOS, WORLD_FRAME
from sphere_servo.ros.params import declare_all, install_set_callback, run
from sphere_servo.ros.qos import CLOCK, COMMAND, writer
from sphere_servo.ros.vectors import ENABLED_QOS
from sphere_servo.sim.arm import CAMERA_FRAME
from std_msgs.msg import Bool, Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

HARDWARE_ID = 'ur5'
PUBLISHERS_CHECK = 1.0  # s (wall) between two looks at the command topic's publishers


class ArmSim(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('arm_sim', **kwargs)
        self.core = core = ArmSimCore(declare_all(self, ArmSimParams))
        self.log = ThrottledLog(self.get_logger())
        # runtime changes: the poses and start_mode (read by the go_* services); the others
        # are read-only
        install_set_callback(self, lambda: core.params, lambda p: setattr(core, 'params', p))
        # QoS of each topic: sphere_servo.ros.qos
        self.pub_image = self.create_publisher(Image, 'camera/image_raw',
                                               writer('camera/image_raw'))
        self.pub_info = self.create_publisher(CameraInfo, 'camera/camera_info',
                                              writer('camera/camera_info'))
        self.pub_joints = self.create_publisher(JointState, 'joint_states',
                                                writer('joint_states'))
        self.pub_pose = self.create_publisher(PoseStamped, 'ground_truth/camera_pose',
                                              writer('ground_truth/camera_pose'))
        self.pub_clock = self.create_publisher(Clock, '/clock', CLOCK)
        self.pub_markers = self.create_publisher(MarkerArray, '~/markers', MARKERS_QOS)
        if core.markers_error:
            self.get_logger().warn(core.markers_error)
        self.sub_cmd = self.create_subscription(TwistStamped, 'camera/cmd_vel', self._on_cmd,
                                                COMMAND)
        self.sub_enabled = self.create_subscription(Bool, 'servo/enabled', self._on_enabled,
                                                    ENABLED_QOS)
        for name, jump in (('~/reset', core.reset), ('~/go_start', lambda: core.go('start')),
                           ('~/go_desired', lambda: core.go('desired'))):
            self.create_service(Trigger, name, self._service(jump, arming=True))
        for name, act in (('~/hold', core.hold), ('~/release', core.release)):
            self.create_service(Trigger, name, self._service(act))
        self.create_timer(PUBLISHERS_CHECK, self._check_publishers,
                          clock=WallClock(clock_type=ClockType.STEADY_TIME))
        self._cmd_publishers: tuple[str, ...] = ()
        self._last = []  # the last published messages, for lockstep re-publishing
        self._last_wall = time.monotonic()  # when they were sent
        frame = core.frame()
        self.status = StatusPublisher(self, HARDWARE_ID, frame.status())
        if core.lockstep:
            self.create_timer(core.params.idle_republish_period, self._republish)
        else:
            self.create_timer(core.dt, self._tick)
        self._publish(frame)
        p = core.params
        self.get_logger().info(
            f'arm_sim: {p.clock_mode} at {p.camera_rate:g} Hz, target {p.target_kind}, '
            f'start q={np.round(core.arm.q, 3).tolist()}, URDF {core.arm.urdf_path}')

    # --- input ----------------------------------------------------------------------
    @guarded
    def _on_cmd(self, msg: TwistStamped, info: dict) -> None:
        st = msg.header.stamp
        out = self.core.on_command(twist_to_array(msg.twist), msg.header.frame_id,
                                   info.get('publication_sequence_number'),
                                   stamp_ns(st.sec, st.nanosec))
        if not out.valid:
            self.log.warn(f'refusing {out.reason}: command refused, not executed, arm stopped')
        if out.frame is not None:
            self._publish(out.frame)

    @guarded
    def _on_enabled(self, msg: Bool) -> None:
        self.core.on_servo_enabled(msg.data)

    @guarded
    def _check_publishers(self) -> None:
        names = tuple(sorted(f'{e.node_namespace.rstrip("/")}/{e.node_name}'
                             for e in self.get_publishers_info_by_topic(self.sub_cmd.topic_name)))
        if len(names) > 1 and names != self._cmd_publishers:
            self.get_logger().warn(f'commands on {self.sub_cmd.topic_name} from '
                                   f'{len(names)} publishers: {", ".join(names)}; one driver at '
                                   'a time (a second one is refused while the first drives)')
        self._cmd_publishers = names
        self.core.on_command_publishers(names)
        if self.sub_enabled.get_publisher_count() == 0:  # a servo that is gone drives nothing
            self.core.on_servo_enabled(False)

    def _service(self, act, arming: bool = False):
        return functools.partial(self._serve, act, arming)

    @guarded_service
    def _serve(self, act, arming: bool, request, response):
        if arming and self.sub_enabled.get_publisher_count() == 0:
            self.core.on_servo_enabled(False)  # no servo (it left, or never started)
        out = act()
        response.success, response.message = out.success, out.message
        if out.frame is not None:
            self._publish(out.frame)
        if out.success:  # one severity per call site (rclpy's rule)
            self.get_logger().info(out.message)
        else:
            self.get_logger().warn(out.message)
        return response

    def go_safe(self, *_) -> None:
        """Stop the arm (the guard's answer to a callback that failed)."""
        self.core.arm.stop()

    @guarded
    def _tick(self) -> None:
        self._publish(self.core.on_tick())

    @guarded
    def _republish(self) -> None:
        idle = time.monotonic() - self._last_wall
        if self.core.republish_due and idle >= self.core.params.idle_republish_period:
            self._send_last()

    def _send_last(self) -> None:
        self._last_wall = time.monotonic()
        for pub, msg in self._last:
            pub.publish(msg)

    # --- output ---------------------------------------------------------------------
    def _publish(self, f: SimFrame) -> None:
        if f.step_error:
            self.get_logger().error(f'simulation step failed, holding still: {f.step_error}')
        if f.render_error:
            self.log.error(f'render failed: {f.render_error}')
        stamp = stamp_from_ns(f.stamp_ns)
        hdr = Header(stamp=stamp, frame_id=CAMERA_FRAME)
        state = self.status.state_msg(f.status(), hdr)
        self._last = [  # the clock too: a node that starts late gets it with the frame
            (self.pub_clock, Clock(clock=stamp)),
            (self.pub_info, camera_info_from_intrinsics(self.core.camera, hdr)),
            (self.pub_joints, JointState(header=Header(stamp=stamp), name=list(f.joint_names),
                                         position=f.q.tolist(), velocity=f.qdot.tolist())),
            (self.pub_pose, PoseStamped(header=Header(stamp=stamp,
                                                      frame_id=self.core.params.target_frame),
                                        pose=pose_from_se3(f.oMc))),
            (self.status.pub_state, state), (self.pub_image, image_from_array(f.image, hdr))]
        self._send_last()
        self.status.note(f.status())
        markers = self.core.markers(f)
        if markers is not None:
            self.pub_markers.publish(marker_array(markers, Header(stamp=stamp,
                                                                  frame_id=WORLD_FRAME)))


def main(args=None):
    run(ArmSim, 'arm_sim', args)


if __name__ == '__main__':
    main()
