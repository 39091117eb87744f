"""``arm_sim``: a simulated UR5 with an eye-in-hand camera looking at a marked sphere.

The kinematics, limits and watchdog are :class:`sphere_servo.sim.arm.ArmModel`; images come
from :class:`sphere_servo.vision.renderer.Renderer`. All topic names are relative (remap or
namespace them as usual).

Subscribes
    ``camera/cmd_vel``      geometry_msgs/Twist   camera twist (v, ω) in the *current camera
                            optical frame*, m/s and rad/s. NaN/inf → ignored with a warning.
Publishes (stamps from the simulation clock, which starts at 1.0 s)
    ``camera/image_raw``    sensor_msgs/Image     rgb8, frame_id ``camera_optical_frame``
    ``camera/camera_info``  sensor_msgs/CameraInfo  the true intrinsics, same header
    ``joint_states``        sensor_msgs/JointState  position and the applied velocity
    ``ground_truth/camera_pose``  geometry_msgs/PoseStamped  pose of the camera optical frame
                            in the target frame, ``oMc`` (header.frame_id = ``target_frame``,
                            default ``target``); ``cMo`` is its inverse
    ``arm_sim/status``      diagnostic_msgs/DiagnosticStatus  level OK/WARN/ERROR, message
                            ``ok|joint_limit|singularity|timeout``, values: ``joints`` (names
                            at a limit), ``sigma_min``, ``scale``, ``sim_time``, ``detail``
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
                  then renders and publishes exactly one image (an invalid command advances
                  the clock with the arm held still, so a loop never stalls). The first image
                  (and the one after a reset/go_* jump) is published at once and *re-published*
                  unchanged (same stamp) every ``idle_republish_period`` wall seconds until
                  the next command arrives, so a subscriber that connects late still gets
                  it; all topics are volatile and reliable, with a history of 30 images
                  and 100 of the other messages.

Poses in parameters are 6 numbers ``[x, y, z, roll, pitch, yaw]`` (metres, radians,
``R = Rz(yaw) Ry(pitch) Rx(roll)``). ``desired_cMo`` / ``start_cMo`` give the target in the
camera frame (``cMo``), ``target_pose`` the target in the robot's ``world`` frame (``wMo``),
``hand_eye`` the camera optical frame in ``tool0`` (``tool0Mc``).
"""
from __future__ import annotations

import math

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, Twist
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, JointState
from std_srvs.srv import Trigger

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.targets import make_target
from sphere_servo.ros.conversions import (camera_info_from_intrinsics, header,
                                            image_from_array, pose_from_se3,
                                            stamp_from_seconds, twist_to_array)
from sphere_servo.ros.params import (Param, ParameterError, declare_all,
                                       install_set_callback, run)
from sphere_servo.sim.arm import CAMERA_FRAME, ArmModel, Status, pose_from_xyz_rpy

DEPTH, IMAGE_DEPTH = 100, 30  # publisher history (messages)
START_TIME = 1.0  # s; stamp 0 means "unset" to many ROS tools
LEVELS = {Status.OK: DiagnosticStatus.OK, Status.SINGULARITY: DiagnosticStatus.WARN,
          Status.JOINT_LIMIT: DiagnosticStatus.WARN, Status.TIMEOUT: DiagnosticStatus.WARN}


PI = math.pi
FIXED = dict(read_only=True)
PARAMS = {
    'clock_mode': Param('realtime', "'realtime' (timer at camera_rate) or 'lockstep' (one "
                        'period and one image per command)', choices=('realtime', 'lockstep'),
                        **FIXED),
    'camera_rate': Param(30.0, 'camera frame rate (Hz); the simulation step is 1/camera_rate',
                         range=(0.1, 1000.0), **FIXED),
    'camera.px': Param(600.0, 'focal length along u (px)', range=(1.0, 1e5), **FIXED),
    'camera.py': Param(600.0, 'focal length along v (px)', range=(1.0, 1e5), **FIXED),
    'camera.u0': Param(320.0, 'principal point u (px)', range=(-1e5, 1e5), **FIXED),
    'camera.v0': Param(240.0, 'principal point v (px)', range=(-1e5, 1e5), **FIXED),
    'camera.width': Param(640, 'image width (px)', range=(1, 8192), **FIXED),
    'camera.height': Param(480, 'image height (px)', range=(1, 8192), **FIXED),
    'hand_eye': Param([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 'tool0Mc: camera optical frame in tool0, '
                      '[x y z roll pitch yaw] (m, rad); identity looks out of the flange',
                      size=6, **FIXED),
    'start_mode': Param('pose', "'pose': start = IK of start_cMo (seeded from the desired "
                        "configuration); 'joints': start = start_joints",
                        choices=('pose', 'joints')),
    'start_joints': Param([0.0, -1.57, 1.57, -1.57, -1.57, 0.0], 'UR5 joint configuration '
                          "(rad): start when start_mode = 'joints', IK seed of desired_cMo "
                          'otherwise', size=6),
    'start_cMo': Param([0.07, 0.12, 0.56, -0.46, 0.40, -0.72], 'start pose of the target in '
                       'the camera, [x y z roll pitch yaw]', size=6),
    'desired_cMo': Param([0.0, 0.0, 0.45, 0.0, 0.0, 0.0], 'desired pose of the target in the '
                         'camera (cMo*), [x y z roll pitch yaw]', size=6),
    'target.kind': Param('special', "'special', 'cc' or 'balloon'",
                         choices=('special', 'cc', 'balloon'), **FIXED),
    'target.radius': Param(0.05, 'sphere radius r (m), special and cc', range=(1e-4, 10.0),
                           **FIXED),
    'target.axes': Param([0.06, 0.055, 0.045], 'balloon ellipsoid semi-axes (m)', size=3,
                         positive=True, **FIXED),
    'target_pose': Param([0.5, 0.1, 0.05, PI, 0.0, -PI / 2], 'wMo: target in the robot world '
                         'frame, [x y z roll pitch yaw]', size=6, **FIXED),
    'target_frame': Param('target', 'frame_id of the ground-truth camera pose', **FIXED),
    'cmd_timeout': Param(0.5, 'watchdog: zero velocity after this long (s, sim time) without '
                         'a command', range=(0.0, 3600.0), **FIXED),
    'damping': Param(0.05, 'maximum damped-least-squares damping (applied at sigma_min = 0)',
                     range=(0.0, 10.0), **FIXED),
    'singular_threshold': Param(0.04, 'sigma_min of the camera Jacobian under which damping '
                                'and slow-down start', range=(0.0, 10.0), **FIXED),
    'singular_stop': Param(0.01, 'sigma_min at which motion towards a singularity stops',
                           range=(0.0, 10.0), **FIXED),
    'velocity_scale': Param(1.0, 'fraction of the URDF joint velocity limits used',
                            range=(0.001, 1.0), **FIXED),
    'idle_republish_period': Param(0.5, 'lockstep: wall period (s) of re-publishing the last '
                                   'image until a command arrives', range=(0.01, 60.0),
                                   **FIXED),
    'urdf_path': Param('', "UR5 URDF; '' = find example-robot-data's", **FIXED),
}


class ArmSim(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('arm_sim', **kwargs)
        self.p = declare_all(self, PARAMS)
        self._setup()
        # runtime changes: the poses and start_mode (read by the go_* services); the others
        # are read-only
        install_set_callback(self, PARAMS, self.p.__setitem__)

    # --- set-up ---------------------------------------------------------------------
    def _setup(self) -> None:
        p = self.p
        if not p['singular_threshold'] > p['singular_stop']:
            raise ParameterError('singular_threshold must be > singular_stop, got '
                                 f"{p['singular_threshold']} <= {p['singular_stop']}")
        self.camera = CameraIntrinsics(px=p['camera.px'], py=p['camera.py'],
                                       u0=p['camera.u0'], v0=p['camera.v0'],
                                       width=p['camera.width'], height=p['camera.height'])
        kind = p['target.kind']
        self.target = (make_target('balloon', axes=tuple(p['target.axes']))
                       if kind == 'balloon' else make_target(kind, p['target.radius']))
        from sphere_servo.vision.renderer import Renderer  # the vision engineer's module
        self.renderer = Renderer(self.camera, self.target)
        self.dt = 1.0 / p['camera_rate']
        self.arm = ArmModel(
            urdf_path=p['urdf_path'] or None, tool0Mc=pose_from_xyz_rpy(
                p['hand_eye'][:3], p['hand_eye'][3:]),
            wMo=pose_from_xyz_rpy(p['target_pose'][:3], p['target_pose'][3:]),
            q0=p['start_joints'], damping=p['damping'],
            singular_threshold=p['singular_threshold'], singular_stop=p['singular_stop'],
            velocity_scale=p['velocity_scale'], cmd_timeout=p['cmd_timeout'])
        q_start = self._named('start')  # raises if IK fails: refused at start
        self._named('desired')
        self.arm.q_start = q_start
        self.arm.reset()

        # history deep enough that a recorder or a monitor falling behind for a second (a
        # loaded machine) loses nothing: a reliable publisher drops what leaves its history
        self.pub_image = self.create_publisher(Image, 'camera/image_raw', IMAGE_DEPTH)
        self.pub_info = self.create_publisher(CameraInfo, 'camera/camera_info', DEPTH)
        self.pub_joints = self.create_publisher(JointState, 'joint_states', DEPTH)
        self.pub_pose = self.create_publisher(PoseStamped, 'ground_truth/camera_pose', DEPTH)
        self.pub_status = self.create_publisher(DiagnosticStatus, 'arm_sim/status', DEPTH)
        self.pub_clock = self.create_publisher(Clock, '/clock', 10)
        self.create_subscription(Twist, 'camera/cmd_vel', self._on_cmd, 10)
        for name, cb in (('~/reset', self._srv_reset), ('~/go_start', self._srv_go_start),
                         ('~/go_desired', self._srv_go_desired), ('~/hold', self._srv_hold)):
            self.create_service(Trigger, name, cb)

        self.lockstep = p['clock_mode'] == 'lockstep'
        self._last = None  # the last published messages, for lockstep re-publishing
        self._waiting = self.lockstep  # re-publish the first image until a command comes
        if self.lockstep:
            self._idle_timer = self.create_timer(p['idle_republish_period'], self._republish)
        else:
            self.create_timer(self.dt, self._tick)
        self._publish_state()
        self.get_logger().info(
            f"arm_sim: {p['clock_mode']} at {p['camera_rate']:g} Hz, target "
            f"{kind}, start q={np.round(self.arm.q, 3).tolist()}, URDF {self.arm.urdf_path}")

    def _named(self, which: str) -> np.ndarray:
        """Joint configuration of the 'start' or 'desired' pose from the current parameters
        (IK); raises ParameterError if the IK does not converge."""
        p = self.p
        if which == 'start' and p['start_mode'] == 'joints':
            return np.asarray(p['start_joints'], dtype=float)
        cMo = p['desired_cMo'] if which == 'desired' else p['start_cMo']
        seed = p['start_joints'] if which == 'desired' else self._named('desired')
        q, ok, err = self.arm.ik_for_cMo(pose_from_xyz_rpy(cMo[:3], cMo[3:]), seed)
        if not ok:
            raise ParameterError(f'no UR5 configuration reaches {which}_cMo={list(cMo)} '
                                 f'(IK residual {err:.3g}); change it or target_pose')
        return q

    # --- command and time -----------------------------------------------------------
    def _on_cmd(self, msg: Twist) -> None:
        v = twist_to_array(msg)
        valid = bool(np.all(np.isfinite(v)))
        if valid:
            self.arm.command(v)
        else:
            self.get_logger().warn(f'ignoring a non-finite camera twist {v.tolist()}',
                                   throttle_duration_sec=1.0)
        if self.lockstep:
            self._waiting = False
            if not valid:  # hold still for this period; the loop gets its image
                self.arm.command(np.zeros(6))
            self._advance()

    def _tick(self) -> None:
        self._advance()

    def _advance(self) -> None:
        try:
            self.arm.step(self.dt)
        except Exception as e:  # noqa: BLE001 - never crash on a bad step; hold still
            self.get_logger().error(f'simulation step failed, holding still: {e}')
            self.arm.stop()
        self._publish_state()

    def _republish(self) -> None:
        if self._waiting and self._last is not None:
            for pub, msg in self._last:
                pub.publish(msg)

    # --- output ---------------------------------------------------------------------
    def _publish_state(self) -> None:
        t = START_TIME + self.arm.t
        hdr = header(t, CAMERA_FRAME)
        self.pub_clock.publish(Clock(clock=stamp_from_seconds(t)))
        cMo = self.arm.cMo()
        try:
            img = self.renderer.render(cMo)
        except Exception as e:  # noqa: BLE001 - a frame we cannot render: black, say why
            self.get_logger().error(f'render failed: {e}', throttle_duration_sec=1.0)
            img = np.zeros((self.camera.height, self.camera.width, 3), np.uint8)
        image = image_from_array(img, hdr)
        info = camera_info_from_intrinsics(self.camera, hdr)
        js = JointState(header=header(t, ''), name=self.arm.joint_names,
                        position=self.arm.q.tolist(), velocity=self.arm.qdot.tolist())
        pose = PoseStamped(header=header(t, self.p['target_frame']),
                           pose=pose_from_se3(cMo.inverse()))
        st = self.arm.info
        status = DiagnosticStatus(
            level=LEVELS[st.status], name='arm_sim', message=st.status.value,
            hardware_id='ur5', values=[
                KeyValue(key='joints', value=','.join(st.joints)),
                KeyValue(key='sigma_min', value=f'{st.sigma_min:.5f}'),
                KeyValue(key='scale', value=f'{st.scale:.4f}'),
                KeyValue(key='sim_time', value=f'{t:.6f}'),
                KeyValue(key='detail', value=st.message)])
        self._last = [(self.pub_info, info), (self.pub_joints, js), (self.pub_pose, pose),
                      (self.pub_status, status), (self.pub_image, image)]
        for pub, msg in self._last:
            pub.publish(msg)

    # --- services -------------------------------------------------------------------
    def _jump(self, q, what: str, response):
        self.arm.set_q(q)
        self.arm.stop()
        self.arm.t += self.dt  # one period passes, so the new image has a new stamp
        self._waiting = self.lockstep
        self._publish_state()
        # the stamp ends the reply, so a caller knows which images show the new pose
        response.success, response.message = True, (
            f'at {what}: q={np.round(q, 4).tolist()}, first image stamped '
            f'{START_TIME + self.arm.t:.9f}')
        self.get_logger().info(response.message)
        return response

    def _srv_reset(self, request, response):
        t = self.arm.t
        self.arm.reset()
        self.arm.t = t
        return self._jump(self.arm.q_start, 'start (reset)', response)

    def _srv_go(self, which: str, response):
        try:
            q = self._named(which)
        except ParameterError as e:
            response.success, response.message = False, str(e)
            return response
        return self._jump(q, which, response)

    def _srv_go_start(self, request, response):
        return self._srv_go('start', response)

    def _srv_go_desired(self, request, response):
        return self._srv_go('desired', response)

    def _srv_hold(self, request, response):
        self.arm.stop()
        response.success, response.message = True, 'command dropped'
        return response


def main(args=None):
    run(ArmSim, 'arm_sim', args)


if __name__ == '__main__':
    main()
