"""
Node parameters without ROS: one typed, frozen dataclass per node, built from its table.

Each field of a node's dataclass carries its :class:`Param` (default, description,
constraints) as metadata, so the dataclass *is* the declared table: the ros layer declares
every entry of :meth:`NodeParams.table` (ROS name → Param) and builds the dataclass with
:meth:`NodeParams.from_mapping`; the bag tools build the same dataclass from a config's node
section. A refused value raises :class:`ParameterError` with a clear message, as
image_tools' cam2image does; rules that tie several parameters together live in the
dataclass's ``validate``, so a runtime change (:meth:`NodeParams.replace`) obeys them too.

Values are immutable: an array parameter is a tuple of floats (of strings for ``sets``).
Every number is range-checked, each entry of an array too. Names that are not parameters
of the node are refused where a mistake is likely (a node's start, a scenario): a misspelt
``-p gian:=5`` would otherwise be ignored without a word (:func:`check_names`).
"""
from __future__ import annotations

import array
from collections.abc import Mapping
import dataclasses
from dataclasses import dataclass, field
import math

import numpy as np

from sphere_servo.core.camera_models import camera_from_camera_info_fields, MODELS
from sphere_servo.core.control import INTERACTION_CHOICES
from sphere_servo.core.features import FEATURE_SETS

PI = math.pi
#: parameters every rclpy node declares itself (Jazzy): known to every node
ROS_PARAMETERS = ('use_sim_time', 'start_type_description_service')
TARGET_KINDS = ('special', 'cc', 'balloon')
_PARAM = 'sphere_servo.param'  # metadata keys of a field
_NAME = 'sphere_servo.name'


class ParameterError(ValueError):
    """A parameter value is refused."""


@dataclass(frozen=True)
class Param:
    """
    One parameter: default, description, and constraints.

    bounds   (lo, hi) inclusive for numbers; for an array, (lo, hi) for every entry or one
             (lo, hi) per entry. choices: allowed strings; size: length of an array
             parameter (its entries must be finite; > 0 too with ``positive``); read_only:
             cannot change after start.
    """

    default: object
    description: str
    bounds: tuple | None = None
    choices: tuple | None = None
    size: int | None = None
    read_only: bool = False
    positive: bool = False


def check(name: str, p: Param, value):
    """Return ``value`` if ``p`` accepts it; raise :class:`ParameterError` otherwise."""
    if p.choices is not None and value not in p.choices:
        raise ParameterError(f'{name} must be one of {list(p.choices)}, got {value!r}')
    if p.size is not None:
        arr = np.asarray(value, dtype=float)
        if arr.shape != (p.size,):
            raise ParameterError(f'{name} needs {p.size} numbers, got {len(value)}')
        if not np.all(np.isfinite(arr)):
            raise ParameterError(f'{name} contains NaN or inf: {list(value)}')
        if p.positive and np.any(arr <= 0):
            raise ParameterError(f'{name} must be > 0, got {list(value)}')
        if p.bounds is not None:
            per_entry = p.bounds if isinstance(p.bounds[0], tuple) else (p.bounds,) * p.size
            for i, (v, (lo, hi)) in enumerate(zip(arr.tolist(), per_entry)):
                if not lo <= v <= hi:
                    raise ParameterError(f'{name}[{i}] must be in [{lo:g}, {hi:g}], got {v} '
                                         f'(in {list(value)})')
        return value
    if isinstance(p.default, (int, float)) and not isinstance(p.default, bool):
        if not math.isfinite(value):
            raise ParameterError(f'{name} must be finite, got {value}')
        if p.bounds is not None and not p.bounds[0] <= value <= p.bounds[1]:
            raise ParameterError(f'{name} must be in [{p.bounds[0]}, {p.bounds[1]}], '
                                 f'got {value}')
    return value


def _typed(name: str, p: Param, value):
    """Return ``value`` in the type of ``p.default`` (an array as a tuple), or refuse it."""
    d = p.default
    if isinstance(d, bool):
        ok = isinstance(value, bool)
    elif isinstance(d, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(d, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = _float(name, value) if ok else value
    elif isinstance(d, str):
        ok = isinstance(value, str)
    elif value is None:  # what ROS gives for `[]`, which has no element type
        raise ParameterError(f'{name} must be a non-empty list like {list(d)}, got an empty '
                             'or unset value')
    else:  # an array: numbers, or strings when the default holds strings
        ok = isinstance(value, (list, tuple, np.ndarray, array.array))
        if ok and d and isinstance(d[0], str):
            ok = all(isinstance(v, str) for v in value)
            value = tuple(value) if ok else value
        elif ok:
            ok = all(isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
                     for v in value)
            value = tuple(_float(name, v) for v in value) if ok else value
    if not ok:
        raise ParameterError(f'{name} must be of the type of {d!r}, got {value!r}')
    return value


def _float(name: str, value) -> float:
    """Return ``float(value)``; ParameterError for an integer beyond a float (YAML has them)."""
    try:
        return float(value)
    except OverflowError:
        raise ParameterError(f'{name} must be a finite number, got an integer of '
                             f'{len(str(abs(int(value))))} digits') from None


def _ros_typed(name: str, p: Param, value) -> None:
    """
    Refuse a params-file value that ROS types otherwise than the parameter's default.

    rcl reads ``1`` as an integer and ``[0, 1.5]`` not at all (a sequence of one type
    only), and rclpy refuses an integer for a declared double: the node would not start.
    """
    d = p.default
    if isinstance(d, float) and isinstance(value, int) and not isinstance(value, bool):
        raise ParameterError(f'{name} must be a floating-point number: ROS reads {value} as '
                             f'an integer, write {_float(name, value)}')
    if isinstance(d, (list, tuple)) and d and isinstance(d[0], float) \
            and isinstance(value, (list, tuple)) \
            and any(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise ParameterError(f'{name} must be floating-point numbers: ROS reads the '
                             f'integers in {list(value)} as integers, write '
                             f'{[_float(name, v) for v in value]}')


def param(default, description: str, *, name: str | None = None, **constraints):
    """
    Declare a field of a :class:`NodeParams` dataclass.

    ``name`` is the ROS parameter name when it is not the field's (``camera.px`` for the
    field ``camera_px``); ``constraints`` are those of :class:`Param`.
    """
    p = Param(default, description, **constraints)
    value = tuple(default) if isinstance(default, list) else default
    return field(default=value, metadata={_PARAM: p, _NAME: name})


def _flatten(values: Mapping, prefix: str = '') -> dict:
    """Nested mappings (a YAML node section) as dotted names, as ROS reads them."""
    out = {}
    for k, v in values.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


@dataclass(frozen=True)
class NodeParams:
    """Base of the nodes' parameter dataclasses (see the module docstring)."""

    @classmethod
    def _fields(cls) -> list[tuple[str, dataclasses.Field]]:
        return [(f.metadata.get(_NAME) or f.name, f) for f in dataclasses.fields(cls)]

    @classmethod
    def table(cls) -> dict[str, Param]:
        """ROS parameter name → :class:`Param`, in declaration order."""
        return {name: f.metadata[_PARAM] for name, f in cls._fields()}

    @classmethod
    def from_mapping(cls, values: Mapping | None = None, strict: bool = False):
        """
        Build the parameters from ROS names → values (nested sections allowed).

        A missing name takes its default; names that are not parameters of the node (e.g.
        ``use_sim_time``) are ignored, unless ``strict`` (values as a params file gives
        them, before ROS reads them): then a name that is neither the node's nor one of
        :data:`ROS_PARAMETERS` is refused (:func:`check_names`), and so is a value ROS
        would type otherwise than the parameter (:func:`_ros_typed`). Raises
        :class:`ParameterError` on a refused value.
        """
        flat = _flatten(values or {})
        if strict:
            check_names(flat, cls.table())
        kw = {}
        for name, f in cls._fields():
            p = f.metadata[_PARAM]
            if strict and name in flat:
                _ros_typed(name, p, flat[name])
            value = _typed(name, p, flat.get(name, p.default))
            kw[f.name] = check(name, p, value)
        return cls(**kw)

    def to_mapping(self) -> dict:
        """ROS parameter name → value (arrays as lists, as ROS declares them)."""
        return {name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
                for name, f in self._fields()}

    def replace(self, changes: Mapping):
        """Return a copy with ``changes`` (ROS names) applied, validated as at start."""
        return type(self).from_mapping({**self.to_mapping(), **changes})

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Check the rules that tie parameters together (ParameterError if one fails)."""


def check_names(names, own, known=ROS_PARAMETERS) -> None:
    """
    Refuse ``names`` that are neither the node's parameters ``own`` nor ``known``.

    ParameterError whose message lists the node's parameters, so a misspelt name is found
    at once.
    """
    own, known = sorted(own), sorted(known)
    unknown = sorted(n for n in names if n not in own and n not in known)
    if unknown:
        raise ParameterError(f'unknown parameter{"s" if len(unknown) > 1 else ""} '
                             f'{", ".join(unknown)}; the parameters are: {", ".join(own)}'
                             + (f' (and {", ".join(known)})' if known else ''))


def check_intrinsics_error(e) -> None:
    """
    Refuse relative intrinsics errors ``(px, py, u0, v0)`` that no camera survives.

    ``px, py``: ``e > −1``, so the focal length ``px·(1 + e)`` stays > 0 (the same rule as
    :meth:`~sphere_servo.core.central.CentralCamera.with_error`). The bounds of the table
    (``|e| ≤ 3`` for u0, v0: a centred principal point ``W/2·(1 + e)`` stays within the
    image's one-image margin, ``core.central.PRINCIPAL_POINT_MARGIN``) come first. What
    depends on the camera itself is refused when its camera_info comes, naming the error.
    """
    for name, v in zip(('px', 'py'), e[:2]):
        if not v > -1.0:
            raise ParameterError(f'intrinsics_error {name} = {v} must be > -1: the focal '
                                 f'length {name}·(1 + e) must stay > 0')


FIXED = {'read_only': True}
#: a pose [x y z roll pitch yaw]: within 100 m, angles within ±2π
POSE_BOUNDS = ((-100.0, 100.0),) * 3 + ((-2 * PI, 2 * PI),) * 3
#: relative intrinsics errors (px, py, u0, v0); see check_intrinsics_error
INTRINSICS_ERROR_BOUNDS = ((-1.0, 1e3), (-1.0, 1e3), (-3.0, 3.0), (-3.0, 3.0))


@dataclass(frozen=True)
class ServoParams(NodeParams):
    """The ``servo`` node's parameters."""

    feature_set: str = param('s_n', 'feature set to servo on', choices=('s_n', 's'), **FIXED)
    r_hat: float = param(0.05, 'estimated sphere radius r̂ (m); any r̂ > 0 is stable '
                         '(paper §III)', bounds=(1e-6, 1e3), **FIXED)
    gain: float = param(0.5, 'constant gain λ (1/s), when adaptive is false',
                        bounds=(1e-6, 1e3), **FIXED)
    adaptive: bool = param(False, "adaptive gain (ViSP's vpAdaptiveGain on ‖s − s*‖∞)",
                           **FIXED)
    lambda_0: float = param(2.0, 'adaptive gain at zero error (1/s)', bounds=(1e-6, 1e3),
                            **FIXED)
    lambda_inf: float = param(0.3, 'adaptive gain at infinite error (1/s)',
                              bounds=(1e-6, 1e3), **FIXED)
    slope_0: float = param(10.0, 'adaptive gain slope at zero error', bounds=(1e-6, 1e6),
                           **FIXED)
    interaction: str = param('current', 'where L̂ is evaluated', choices=INTERACTION_CHOICES,
                             **FIXED)
    v_max: float = param(0.2, 'translational speed limit (m/s); the twist is scaled as a '
                         'whole', bounds=(1e-6, 10.0), **FIXED)
    w_max: float = param(1.0, 'rotational speed limit (rad/s)', bounds=(1e-6, 100.0),
                         **FIXED)
    tol: float = param(1e-3, 'converged when ‖s − s*‖₂ < tol', bounds=(1e-12, 10.0), **FIXED)
    timeout: float = param(0.5, 'zero twists when no usable features came for this long '
                           '(wall s)', bounds=(0.01, 60.0), **FIXED)
    max_image_age: float = param(0.2, 'skip features whose image is older than this on the '
                                 "node's clock (s); 0: only the current frame (lockstep)",
                                 bounds=(0.0, 60.0), **FIXED)
    future_tolerance: float = param(0.2, 'refuse features stamped later than this ahead of '
                                    "the node's clock (s); at least one frame period, as "
                                    'the clock and the images come on different topics',
                                    bounds=(0.0, 60.0), **FIXED)
    start_enabled: bool = param(True, 'servo at once; false: send zero twists until '
                                '~/enable', **FIXED)
    lockstep: bool = param(False, 'the arm is a lockstep simulator (each twist steps it, '
                           'and it does not move between twists): the watchdog reports '
                           'waiting/stale but sends no twist, which would step it', **FIXED)

    def validate(self) -> None:
        """Check that the adaptive gain decreases (λ₀ > λ∞), when it is used."""
        if self.adaptive and not self.lambda_0 > self.lambda_inf:
            raise ParameterError('the adaptive gain needs lambda_0 > lambda_inf, got '
                                 f'{self.lambda_0} <= {self.lambda_inf}')


#: the ``image_reliability`` parameter of the nodes that read the camera's topics
IMAGE_RELIABILITY = (
    'reliable', "reliability of the camera's readers (images, camera_info): 'reliable' (the "
    "pipeline's: lockstep needs every image) or 'best_effort' (also matches a camera that "
    'publishes best effort, as SensorDataQoS does, which a reliable reader never matches)')
RELIABILITIES = ('reliable', 'best_effort')


@dataclass(frozen=True)
class FeaturesParams(NodeParams):
    """The ``features`` node's parameters."""

    target_kind: str = param('special', "target: 'special', 'cc' or 'balloon' (a balloon is "
                             'servoed as a special sphere)', choices=TARGET_KINDS, **FIXED)
    target_radius: float = param(0.05, 'radius r (m) of the target model, for '
                                 'desired_source pose', bounds=(1e-4, 10.0), **FIXED)
    sets: tuple[str, ...] = param(['s_n'], 'feature sets to publish, among '
                                  f'{list(FEATURE_SETS)}', **FIXED)
    desired_source: str = param('teach', 'where the desired features come from',
                                choices=('teach', 'pose', 'image'), **FIXED)
    desired_cMo: tuple[float, ...] = param(
        [0.0, 0.0, 0.45, 0.0, 0.0, 0.0], 'desired target pose in the camera [x y z roll '
        'pitch yaw] (desired_source pose)', size=6, bounds=POSE_BOUNDS, **FIXED)
    desired_image: str = param('', 'desired image file (desired_source image)', **FIXED)
    intrinsics_error: tuple[float, ...] = param(
        [0.0, 0.0, 0.0, 0.0], 'relative errors (px, py, u0, v0) for detecting the desired '
        'image', size=4, bounds=INTRINSICS_ERROR_BOUNDS, **FIXED)
    desired_file: str = param('', 'teach: the file the taught desired is kept in and '
                              "reloaded from at start (survives a restart); '': none",
                              **FIXED)
    image_reliability: str = param(*IMAGE_RELIABILITY, choices=RELIABILITIES, **FIXED)

    def validate(self) -> None:
        """Check ``sets`` (known feature sets, at least one) and ``intrinsics_error``."""
        check_intrinsics_error(self.intrinsics_error)
        for name in self.sets:
            if name not in FEATURE_SETS:
                raise ParameterError(f'sets: unknown feature set {name!r}, use '
                                     f'{list(FEATURE_SETS)}')
        if not self.sets:
            raise ParameterError('sets must name at least one feature set')


@dataclass(frozen=True)
class DetectorParams(NodeParams):
    """The ``detector`` node's parameters."""

    target_kind: str = param('special', 'target whose colours and marks to look for',
                             choices=TARGET_KINDS, **FIXED)
    intrinsics_error: tuple[float, ...] = param(
        [0.0, 0.0, 0.0, 0.0], 'relative errors (px, py, u0, v0) applied to camera_info '
        '(calibration-error experiment)', size=4, bounds=INTRINSICS_ERROR_BOUNDS, **FIXED)
    publish_overlay: bool = param(False, 'publish detector/overlay (costs a copy and a draw)')
    image_transport: str = param('raw', "'raw': sensor_msgs/Image on camera/image_raw; "
                                 "'compressed': sensor_msgs/CompressedImage (JPEG, PNG) on "
                                 'camera/image_raw/compressed, as image_transport names it',
                                 choices=('raw', 'compressed'), **FIXED)
    image_reliability: str = param(*IMAGE_RELIABILITY, choices=RELIABILITIES, **FIXED)

    def validate(self) -> None:
        """Check ``intrinsics_error`` (:func:`check_intrinsics_error`)."""
        check_intrinsics_error(self.intrinsics_error)


@dataclass(frozen=True)
class ArmSimParams(NodeParams):
    """The ``arm_sim`` node's parameters (poses: [x y z roll pitch yaw], m and rad)."""

    clock_mode: str = param('realtime', "'realtime' (timer at camera_rate) or 'lockstep' "
                            '(one period and one image per command)',
                            choices=('realtime', 'lockstep'), **FIXED)
    camera_rate: float = param(30.0, 'camera frame rate (Hz); the simulation step is '
                               '1/camera_rate', bounds=(0.1, 1000.0), **FIXED)
    camera_px: float = param(600.0, 'focal length along u (px)', bounds=(1.0, 1e5),
                             name='camera.px', **FIXED)
    camera_py: float = param(600.0, 'focal length along v (px)', bounds=(1.0, 1e5),
                             name='camera.py', **FIXED)
    camera_u0: float = param(320.0, 'principal point u (px)', bounds=(-1e5, 1e5),
                             name='camera.u0', **FIXED)
    camera_v0: float = param(240.0, 'principal point v (px)', bounds=(-1e5, 1e5),
                             name='camera.v0', **FIXED)
    camera_width: int = param(640, 'image width (px)', bounds=(1, 8192), name='camera.width',
                              **FIXED)
    camera_height: int = param(480, 'image height (px)', bounds=(1, 8192),
                               name='camera.height', **FIXED)
    camera_model: str = param('plumb_bob', "camera model, CameraInfo's distortion_model: "
                              "'plumb_bob' (pinhole), 'equidistant' (fisheye, Kannala–Brandt), "
                              "'unified' (catadioptric or fisheye, Mei)", choices=MODELS,
                              name='camera.model', **FIXED)
    camera_d: tuple[float, ...] = param(
        [0.0, 0.0, 0.0, 0.0, 0.0], 'distortion coefficients: plumb_bob k1 k2 t1 t2 k3, '
        'equidistant k1 k2 k3 k4, unified k1 k2 p1 p2 (ξ is camera.xi); all zero: none',
        name='camera.d', **FIXED)
    camera_xi: float = param(0.0, "the unified model's ξ (0: a pinhole, 0.9: a hyperbolic "
                             'mirror, 1: a parabolic one)', bounds=(0.0, 10.0), name='camera.xi',
                             **FIXED)
    hand_eye: tuple[float, ...] = param(
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 'tool0Mc: camera optical frame in tool0, [x y z roll '
        'pitch yaw] (m, rad); identity looks out of the flange', size=6,
        bounds=((-1.0, 1.0),) * 3 + POSE_BOUNDS[3:], **FIXED)
    start_mode: str = param('pose', "'pose': start = IK of start_cMo (seeded from the "
                            "desired configuration); 'joints': start = start_joints",
                            choices=('pose', 'joints'))
    start_joints: tuple[float, ...] = param(
        [0.0, -1.57, 1.57, -1.57, -1.57, 0.0], 'UR5 joint configuration (rad): start when '
        "start_mode = 'joints', IK seed of desired_cMo otherwise", size=6,
        bounds=(-2 * PI, 2 * PI))
    start_cMo: tuple[float, ...] = param(
        [0.07, 0.12, 0.56, -0.46, 0.40, -0.72], 'start pose of the target in the camera, '
        '[x y z roll pitch yaw]', size=6, bounds=POSE_BOUNDS)
    desired_cMo: tuple[float, ...] = param(
        [0.0, 0.0, 0.45, 0.0, 0.0, 0.0], 'desired pose of the target in the camera (cMo*), '
        '[x y z roll pitch yaw]', size=6, bounds=POSE_BOUNDS)
    target_kind: str = param('special', "'special', 'cc' or 'balloon'", choices=TARGET_KINDS,
                             name='target.kind', **FIXED)
    target_radius: float = param(0.05, 'sphere radius r (m), special and cc',
                                 bounds=(1e-4, 10.0), name='target.radius', **FIXED)
    target_axes: tuple[float, ...] = param([0.06, 0.055, 0.045], 'balloon ellipsoid '
                                           'semi-axes (m)', size=3, positive=True,
                                           bounds=(0.0, 10.0),
                                           name='target.axes', **FIXED)
    target_pose: tuple[float, ...] = param(
        [0.5, 0.1, 0.05, PI, 0.0, -PI / 2], 'wMo: target in the robot world frame, [x y z '
        'roll pitch yaw]', size=6, bounds=POSE_BOUNDS, **FIXED)
    target_frame: str = param('target', 'frame_id of the ground-truth camera pose', **FIXED)
    cmd_timeout: float = param(0.2, 'watchdog: zero velocity after this long (s, sim time) '
                               'without a command', bounds=(0.0, 3600.0), **FIXED)
    damping: float = param(0.05, 'maximum damped-least-squares damping (applied at '
                           'sigma_min = 0)', bounds=(0.0, 10.0), **FIXED)
    singular_threshold: float = param(0.04, 'sigma_min of the camera Jacobian under which '
                                      'damping and slow-down start', bounds=(0.0, 10.0),
                                      **FIXED)
    singular_stop: float = param(0.01, 'sigma_min at which motion towards a singularity '
                                 'stops', bounds=(0.0, 10.0), **FIXED)
    velocity_scale: float = param(1.0, 'fraction of the URDF joint velocity limits used',
                                  bounds=(0.001, 1.0), **FIXED)
    idle_republish_period: float = param(0.5, 'lockstep: wall period (s) of re-publishing '
                                         'the last image until a command arrives',
                                         bounds=(0.01, 60.0), **FIXED)
    urdf_path: str = param('', "UR5 URDF; '' = find example-robot-data's", **FIXED)
    markers_rate: float = param(10.0, 'rate (Hz of sim time) of ~/markers, the 3-D scene '
                                'for RViz and Foxglove; 0: not published', bounds=(0.0, 1000.0),
                                **FIXED)
    markers_mesh_uris: str = param('package', "the robot markers' mesh URIs: 'package' "
                                   '(package://example-robot-data/..., found by a ROS install '
                                   "of example-robot-data) or 'file' (file:// URIs of this "
                                   "machine's meshes, for a viewer on this machine without "
                                   'it)', choices=('package', 'file'), **FIXED)

    def camera(self):
        """
        Return the simulated camera, as the CameraInfo factory builds it from these values.

        ``camera.d`` all zero, of any length, is no distortion. ParameterError when the
        factory refuses the camera (a wrong number of coefficients, a fold in the image…).
        """
        n = {'plumb_bob': 5, 'equidistant': 4, 'unified': 4}[self.camera_model]
        d = list(self.camera_d)
        if not any(d):
            d = [0.0] * n
        if self.camera_model == 'unified':
            d = [self.camera_xi] + d
        k = [self.camera_px, 0.0, self.camera_u0, 0.0, self.camera_py, self.camera_v0,
             0.0, 0.0, 1.0]
        try:
            return camera_from_camera_info_fields(self.camera_width, self.camera_height, k, d,
                                                  self.camera_model)
        except ValueError as exc:
            raise ParameterError(f'camera: {exc}') from None

    def validate(self) -> None:
        """Check the camera, and that the slow-down starts before the stop."""
        self.camera()
        if not self.singular_threshold > self.singular_stop:
            raise ParameterError('singular_threshold must be > singular_stop, got '
                                 f'{self.singular_threshold} <= {self.singular_stop}')


# the pipeline's nodes and their parameters, by node name (the sections of a params file)
NODE_PARAMS: dict[str, type[NodeParams]] = {
    'arm_sim': ArmSimParams, 'detector': DetectorParams, 'features': FeaturesParams,
    'servo': ServoParams}
