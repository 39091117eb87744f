"""
``arm_sim``: a simulated UR5 with an eye-in-hand camera looking at a marked sphere.

The kinematics, limits and watchdog are :class:`sphere_servo.sim.arm.ArmModel`; images come
from :class:`sphere_servo.vision.renderer.Renderer`. All topic names are relative (remap or
namespace them as usual).

Subscribes
    ``camera/cmd_vel``      geometry_msgs/TwistStamped  camera twist (v, ω) in the *current
                            camera optical frame*, m/s and rad/s: ``header.frame_id`` must be
                            ``camera_optical_frame``. Another frame, NaN or inf → refused
                            with a warning (throttled) and not executed (in lockstep the
                            period passes with the arm held still).
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
                            the last command was refused), ``step_error``, ``render_error``
    ``/diagnostics``        diagnostic_msgs/DiagnosticArray  the same status, on change and
                            at 1 Hz (hardware_id ``ur5``)
    ``/clock``              rosgraph_msgs/Clock   the simulation time (both clock modes)
Services (std_srvs/Trigger; private, e.g. ``/arm_sim/go_desired``)
    ``~/reset``        start configuration, at rest, watchdog re-armed
    ``~/go_start``     jump to the start configuration (IK of ``start_cMo`` when
                       ``start_mode = 'pose'``; parameters are re-read, so set ``start_cMo``
                       then call this to go to a *given* camera pose)
    ``~/go_desired``   jump to the desired configuration (IK of ``desired_cMo``)
    ``~/hold``         drop the current command (the arm stops at once)

Clock modes (parameter ``clock_mode``)
    ``realtime``  a wall timer at ``camera_rate`` advances the simulation one period per tick
                  under the last command, then renders and publishes.
    ``lockstep``  each received command advances the simulation exactly one camera period,
                  then renders and publishes exactly one image (a refused command advances
                  the clock with the arm held still, so a loop never stalls). The first image
                  (and the one after a reset/go_* jump) is published at once and *re-published*
                  unchanged (same stamp) every ``idle_republish_period`` wall seconds until
                  the next command arrives, so a subscriber that connects late still gets
                  it. The QoS of each topic is :mod:`sphere_servo.ros.qos`'s (all
                  reliable and volatile).

Poses in parameters are 6 numbers ``[x, y, z, roll, pitch, yaw]`` (metres, radians,
``R = Rz(yaw) Ry(pitch) Rx(roll)``). ``desired_cMo`` / ``start_cMo`` give the target in the
camera frame (``cMo``), ``target_pose`` the target in the robot's ``world`` frame (``wMo``),
``hand_eye`` the camera optical frame in ``tool0`` (``tool0Mc``). The logic (stepping,
jumps, re-publishing) is :class:`~sphere_servo.pipeline.arm_sim.ArmSimCore`'s.
"""
from __future__ import annotations

from geometry_msgs.msg import PoseStamped, TwistStamped
import numpy as np
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from sphere_servo.pipeline.arm_sim import ArmSimCore, SimFrame
from sphere_servo.pipeline.params import ArmSimParams
from sphere_servo.ros.conversions import (camera_info_from_intrinsics, image_from_array,
                                          pose_from_se3, stamp_from_ns, twist_to_array)
from sphere_servo.ros.diagnostics import StatusPublisher
from sphere_servo.ros.params import declare_all, install_set_callback, run
from sphere_servo.ros.qos import CLOCK, COMMAND, MONITOR, SENSOR
from sphere_servo.sim.arm import CAMERA_FRAME
from std_msgs.msg import Header
from std_srvs.srv import Trigger

HARDWARE_ID = 'ur5'


class ArmSim(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('arm_sim', **kwargs)
        self.core = core = ArmSimCore(declare_all(self, ArmSimParams))
        # runtime changes: the poses and start_mode (read by the go_* services); the others
        # are read-only
        install_set_callback(self, lambda: core.params, lambda p: setattr(core, 'params', p))
        # QoS of each topic: sphere_servo.ros.qos
        self.pub_image = self.create_publisher(Image, 'camera/image_raw', SENSOR)
        self.pub_info = self.create_publisher(CameraInfo, 'camera/camera_info', SENSOR)
        self.pub_joints = self.create_publisher(JointState, 'joint_states', MONITOR)
        self.pub_pose = self.create_publisher(PoseStamped, 'ground_truth/camera_pose', MONITOR)
        self.pub_clock = self.create_publisher(Clock, '/clock', CLOCK)
        self.create_subscription(TwistStamped, 'camera/cmd_vel', self._on_cmd, COMMAND)
        for name, jump in (('~/reset', core.reset), ('~/go_start', lambda: core.go('start')),
                           ('~/go_desired', lambda: core.go('desired')),
                           ('~/hold', core.hold)):
            self.create_service(Trigger, name, self._service(jump))
        self._last = []  # the last published messages, for lockstep re-publishing
        frame = core.frame()
        self.status = StatusPublisher(self, HARDWARE_ID, frame.status())
        if core.lockstep:
            self.create_timer(core.params.idle_republish_period, self._republish)
        else:
            self.create_timer(core.dt, lambda: self._publish(core.on_tick()))
        self._publish(frame)
        p = core.params
        self.get_logger().info(
            f'arm_sim: {p.clock_mode} at {p.camera_rate:g} Hz, target {p.target_kind}, '
            f'start q={np.round(core.arm.q, 3).tolist()}, URDF {core.arm.urdf_path}')

    # --- input ----------------------------------------------------------------------
    def _on_cmd(self, msg: TwistStamped) -> None:
        out = self.core.on_command(twist_to_array(msg.twist), msg.header.frame_id)
        if not out.valid:
            self.get_logger().warn(f'refusing {out.reason}: not executed, arm stopped',
                                   throttle_duration_sec=1.0)
        if out.frame is not None:
            self._publish(out.frame)

    def _service(self, jump):
        def callback(request, response):
            out = jump()
            response.success, response.message = out.success, out.message
            if out.frame is not None:
                self._publish(out.frame)
                self.get_logger().info(out.message)
            return response
        return callback

    def _republish(self) -> None:
        if self.core.republish_due:
            for pub, msg in self._last:
                pub.publish(msg)

    # --- output ---------------------------------------------------------------------
    def _publish(self, f: SimFrame) -> None:
        if f.step_error:
            self.get_logger().error(f'simulation step failed, holding still: {f.step_error}')
        if f.render_error:
            self.get_logger().error(f'render failed: {f.render_error}',
                                    throttle_duration_sec=1.0)
        stamp = stamp_from_ns(f.stamp_ns)
        self.pub_clock.publish(Clock(clock=stamp))
        hdr = Header(stamp=stamp, frame_id=CAMERA_FRAME)
        state = self.status.state_msg(f.status(), hdr)
        self._last = [
            (self.pub_info, camera_info_from_intrinsics(self.core.camera, hdr)),
            (self.pub_joints, JointState(header=Header(stamp=stamp), name=list(f.joint_names),
                                         position=f.q.tolist(), velocity=f.qdot.tolist())),
            (self.pub_pose, PoseStamped(header=Header(stamp=stamp,
                                                      frame_id=self.core.params.target_frame),
                                        pose=pose_from_se3(f.oMc))),
            (self.status.pub_state, state), (self.pub_image, image_from_array(f.image, hdr))]
        for pub, msg in self._last:
            pub.publish(msg)
        self.status.note(f.status())


def main(args=None):
    run(ArmSim, 'arm_sim', args)


if __name__ == '__main__':
    main()
