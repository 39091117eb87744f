"""``features``: measurements → the paper's feature sets, their desired values and errors.

Subscribes
    ``detector/measurement``  sensor_msgs/JointState  (see :mod:`sphere_servo.ros.vectors`)
    ``camera/camera_info``    sensor_msgs/CameraInfo  only for ``desired_source: image``
Publishes (header = the image's header)
    ``features/<set>``        sensor_msgs/JointState  for each set in ``sets`` (default s_n):
                              position = s, velocity = s*, effort = s − s*; empty = target or
                              a mark lost. Nothing is published before a desired is set.
Services
    ``~/teach``               std_srvs/Trigger  the latest measurement becomes the desired
                              one (teach by showing)

Desired features (``desired_source``):
    ``teach``  from the ``~/teach`` service (default);
    ``pose``   from ``desired_cMo`` = [x y z roll pitch yaw] (m, rad; R = Rz Ry Rx) and the
               target model (exact projection; spherical targets only);
    ``image``  from the image file ``desired_image``, detected with the intrinsics of the
               first ``camera_info`` (with ``intrinsics_error`` applied, as the detector does).
"""
from __future__ import annotations

from pathlib import Path

import cv2
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, JointState
from std_srvs.srv import Trigger

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.features import FEATURE_SETS, make_feature_set
from sphere_servo.core.geometry import GeometryError
from sphere_servo.core.measurement import Observation, observe
from sphere_servo.core.targets import make_target
from sphere_servo.ros.params import Param, ParameterError, declare_all, run
from sphere_servo.ros.vectors import features_msg, observation_from_measurement
from sphere_servo.sim.arm import pose_from_xyz_rpy
from sphere_servo.vision.detector import Detector

PARAMS = {
    'target_kind': Param('special', "target: 'special', 'cc' or 'balloon' (a balloon is "
                         'servoed as a special sphere)', choices=('special', 'cc', 'balloon'),
                         read_only=True),
    'target_radius': Param(0.05, 'radius r (m) of the target model, for desired_source pose',
                           range=(1e-4, 10.0), read_only=True),
    'sets': Param(['s_n'], f'feature sets to publish, among {list(FEATURE_SETS)}',
                  read_only=True),
    'desired_source': Param('teach', 'where the desired features come from',
                            choices=('teach', 'pose', 'image'), read_only=True),
    'desired_cMo': Param([0.0, 0.0, 0.45, 0.0, 0.0, 0.0], 'desired target pose in the camera '
                         '[x y z roll pitch yaw] (desired_source pose)', size=6,
                         read_only=True),
    'desired_image': Param('', 'desired image file (desired_source image)', read_only=True),
    'intrinsics_error': Param([0.0, 0.0, 0.0, 0.0], 'relative errors (px, py, u0, v0) for '
                              'detecting the desired image', size=4, read_only=True),
}


class FeaturesNode(Node):
    """See the module docstring."""

    def __init__(self):
        super().__init__('features')
        self.p = p = declare_all(self, PARAMS)
        for name in p['sets']:
            if name not in FEATURE_SETS:
                raise ParameterError(f'sets: unknown feature set {name!r}, use '
                                     f'{list(FEATURE_SETS)}')
        if not p['sets']:
            raise ParameterError('sets must name at least one feature set')
        self.target = make_target(p['target_kind'], radius=p['target_radius']) \
            if p['target_kind'] != 'balloon' else make_target('balloon')
        self.kind = self.target.kind
        self.sets: dict = {}
        self.latest: JointState | None = None
        self.pubs = {name: self.create_publisher(JointState, f'features/{name}', 100)
                     for name in p['sets']}
        self.create_subscription(JointState, 'detector/measurement', self._on_measurement, 10)
        self.create_service(Trigger, '~/teach', self._srv_teach)
        if p['desired_source'] == 'pose':
            if not self.target.is_sphere:
                raise ParameterError("desired_source 'pose' needs a spherical target model")
            cMo = pose_from_xyz_rpy(p['desired_cMo'][:3], p['desired_cMo'][3:])
            try:
                self._set_desired(observe(cMo, self.target))
            except GeometryError as exc:
                raise ParameterError(f'desired_cMo does not show the target: {exc}') from None
        elif p['desired_source'] == 'image':
            path = Path(p['desired_image'])
            if not path.is_file():
                raise ParameterError(f'desired_image {str(path)!r} is not a file')
            self._desired_bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if self._desired_bgr is None:
                raise ParameterError(f'desired_image {str(path)!r} is not a readable image')
            self._info_sub = self.create_subscription(CameraInfo, 'camera/camera_info',
                                                      self._on_info_for_image, 10)
        else:
            self.get_logger().info('waiting for ~/teach to set the desired features')

    def _set_desired(self, obs: Observation) -> None:
        """Anchor every published set on ``obs`` (raises GeometryError if it cannot be)."""
        self.sets = {name: make_feature_set(name, obs) for name in self.p['sets']}
        s_n = self.sets.get('s_n')
        self.get_logger().info('desired features set' + (
            f': s*_n,t = {s_n.desired[:3].round(4).tolist()}' if s_n else ''))

    def _on_info_for_image(self, msg: CameraInfo) -> None:
        if self.sets:
            return
        try:
            cam = CameraIntrinsics.from_camera_info_fields(msg.width, msg.height, msg.k, msg.d)
            cam = cam.with_error(*self.p['intrinsics_error'])
            det = Detector.for_target(self.target).detect(self._desired_bgr, 'bgr8', cam)
            self._set_desired(det.to_observation(self.kind))
        except (ValueError, GeometryError) as exc:
            self.get_logger().error(f'desired image {self.p["desired_image"]!r} unusable: '
                                    f'{exc}', throttle_duration_sec=5.0)

    def _srv_teach(self, request, response):
        if self.latest is None:
            response.success, response.message = False, 'no measurement received yet'
            return response
        try:
            self._set_desired(observation_from_measurement(self.latest, self.kind))
        except GeometryError as exc:
            response.success, response.message = False, f'cannot teach this image: {exc}'
            return response
        s = self.latest.header.stamp
        response.success = True
        response.message = f'desired features taught from the image stamped {s.sec}.{s.nanosec:09d}'
        return response

    def _on_measurement(self, msg: JointState) -> None:
        self.latest = msg
        if not self.sets:
            return
        try:
            obs = observation_from_measurement(msg, self.kind)
            out = {name: (fs.features(obs), fs.desired) for name, fs in self.sets.items()}
        except GeometryError as exc:
            self.get_logger().warn(f'target lost: {exc}', throttle_duration_sec=2.0)
            out = {name: (None, None) for name in self.sets}
        for name, (s, s_star) in out.items():
            self.pubs[name].publish(features_msg(name, msg.header, s, s_star))


def main(args=None):
    run(FeaturesNode, 'features', args)


if __name__ == '__main__':
    main()
