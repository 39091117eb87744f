"""
The arm simulator's logic without ROS: stepping, jumps, and what each step shows.

:class:`ArmSimCore` wraps :class:`~sphere_servo.sim.arm.ArmModel` (kinematics, limits,
watchdog) and the :class:`~sphere_servo.vision.renderer.Renderer`; each step or jump
yields a :class:`SimFrame`, everything the node publishes for one image.

Clock modes (``clock_mode``):

- ``realtime``: :meth:`ArmSimCore.on_tick` (a wall timer at ``camera_rate``) advances the
  simulation one period under the last command; a command only replaces that command.
- ``lockstep``: each command advances the simulation exactly one period and yields exactly
  one frame (an invalid or refused command advances the clock with the arm held still, so a
  loop never stalls). The first frame, and the one after a jump, is *re-published*
  unchanged (same stamp) until the next command arrives, so a subscriber that connects late
  still gets it; so is the frame after a command while a servo is enabled
  (:attr:`ArmSimCore.republish_due`), so that a pipeline that lost it (a node restarted)
  gets it again: the servo answers a stamp once, so the copies step nothing. With no servo
  enabled (the run over) the arm falls quiet. A command stamped neither 0 (no image) nor
  with the last frame's time answers another pose's image (from before a jump): refused, it
  steps nothing, so one frame stays in flight whenever such a late answer arrives.

Commands are camera twists in :data:`~sphere_servo.sim.arm.CAMERA_FRAME` (the current
camera optical frame). A refused command is not executed and stops the arm at once (zero
velocity from the next step; in lockstep the period passes with the arm held still): one
that is not finite, beyond the arm's physical bound (``ArmModel.check_twist``) or in
another frame; any command while the arm is held (:meth:`ArmSimCore.hold`) or in the
``error`` state; and a command from a second publisher (:meth:`ArmSimCore.on_command`'s
``seq``: one driver at a time).

Jumps (the node's services): ``reset`` (start configuration, at rest, watchdog re-armed,
hold released, sim time kept), ``go_start`` / ``go_desired`` (the IK of ``start_cMo`` /
``desired_cMo``, from the parameters as they are now). A jump lets one period pass, so the
new image has a new stamp, which ends the reply. Arming rule: a jump is refused while the
servo is enabled (:meth:`ArmSimCore.on_servo_enabled`, from the servo's latched
``servo/enabled``): the arm must not be moved under a servo that drives it.
``hold`` drops the command and latches: every command is refused until ``release`` or
``reset``.

The 3-D scene for ROS viewers (:meth:`ArmSimCore.markers`): the
:class:`~sphere_servo.sim.scene.Scene` of the parameters (the UR5's link meshes at the
frame's joint state, the target and its marks, the camera's frustum, the camera path since
the last jump, the desired camera of ``desired_cMo``), at the first frame, after each jump
and then every ``1/markers_rate`` s of sim time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from sphere_servo.core.central import CentralCamera
from sphere_servo.core.targets import make_target, Target
from sphere_servo.core.types import Image
from sphere_servo.pipeline.common import Level, NodeStatus, Reply
from sphere_servo.pipeline.params import ArmSimParams, ParameterError
from sphere_servo.sim.arm import (ArmModel, CAMERA_FRAME, pose_from_xyz_rpy, Status, StepInfo,
                                  TwistError)
from sphere_servo.sim.scene import CameraPath, MarkerSpec, Scene, SceneError
from sphere_servo.vision.renderer import Renderer

START_TIME = 1.0  # s; stamp 0 means "unset" to many ROS tools
#: the sequence number of an RMW that has none (rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_
#: UNSUPPORTED): every message the same, so it tells nothing (it refused all but one a second)
SEQ_UNSUPPORTED = 2 ** 64 - 1
PATH_POINTS = 500  # the camera path's markers keep at most this many points
HELD = 'held: commands are refused until ~/release or ~/reset'
SERVO_ENABLED = ('refused: the servo is enabled (servo/enabled): disable it first '
                 '(/servo/enable false); a jump under a servo that drives the arm is unsafe')
LEVELS = {Status.OK: Level.OK, Status.SINGULARITY: Level.WARN,
          Status.JOINT_LIMIT: Level.WARN, Status.TIMEOUT: Level.WARN,
          Status.ERROR: Level.ERROR}


@dataclass(frozen=True)
class SimFrame:
    """
    One image and what goes with it, at sim time ``t`` (s, from :data:`START_TIME`).

    image        (H, W, 3) rgb8; black when it could not be rendered (``render_error``).
    oMc          the camera optical frame in the target frame (ground truth).
    q, qdot      joint positions and the applied velocities.
    info         what the last step did (status, joints at a limit, σ_min, scale).
    step_error   why the last step failed, the arm then held still ('' if it did not).
    command_error  why the last command was refused ('' if it was not).
    held         the hold is latched: commands are refused until release or reset.
    command_publishers  the publishers of commands, when there are more than one.
    """

    t: float
    image: Image
    oMc: pin.SE3
    joint_names: tuple[str, ...]
    q: np.ndarray
    qdot: np.ndarray
    info: StepInfo
    render_error: str = ''
    step_error: str = ''
    command_error: str = ''
    held: bool = False
    command_publishers: tuple[str, ...] = ()

    @property
    def stamp_ns(self) -> int:
        """Return the stamp of every message of the frame."""
        return int(round(self.t * 1e9))

    @property
    def level(self) -> Level:
        """
        Return how serious the frame's status is.

        ERROR when the step or the render failed, or the arm is in error; WARN at a limit,
        near a singularity, on a timeout, after a refused command, while held, or with
        commands from more than one publisher; OK else.
        """
        if self.step_error or self.render_error:
            return Level.ERROR
        warn = self.command_error or self.held or len(self.command_publishers) > 1
        return max(LEVELS[self.info.status], Level.WARN if warn else Level.OK)

    def status_values(self) -> dict[str, str]:
        """Return the status values, key → text, in the published order."""
        st = self.info
        v = {'joints': ','.join(st.joints), 'sigma_min': f'{st.sigma_min:.5f}',
             'scale': f'{st.scale:.4f}', 'sim_time': f'{self.t:.6f}', 'detail': st.message}
        for key, text in (('command_error', self.command_error),
                          ('step_error', self.step_error), ('render_error', self.render_error)):
            if text:
                v[key] = text
        if self.held:
            v['hold'] = HELD
        if len(self.command_publishers) > 1:
            v['command_publishers'] = ','.join(self.command_publishers)
        return v

    def status(self) -> NodeStatus:
        """Return the node's status at this frame, whose state is the arm's step ``Status``."""
        return NodeStatus(self.info.status, self.level, self.status_values())


@dataclass(frozen=True)
class Jump(Reply):
    """The outcome of a service, and the frame at the new pose (if the arm jumped)."""

    frame: SimFrame | None = None


@dataclass(frozen=True)
class CommandOutcome:
    """
    A received twist: whether it was executed, and the frame it produced (lockstep).

    ``reason``: why it was refused ('' when it was executed).
    """

    valid: bool
    frame: SimFrame | None = None
    reason: str = ''


def frame_refusal(frame_id: str) -> str:
    """
    Return why a camera twist in frame ``frame_id`` is refused ('' if it is not).

    Its values are the arm's to judge (``ArmModel.check_twist``: 6 finite numbers within
    the arm's physical bound).
    """
    if frame_id != CAMERA_FRAME:
        return (f'a camera twist in frame {frame_id!r}: arm_sim takes twists in '
                f'{CAMERA_FRAME!r} only')
    return ''


def sim_camera(p: ArmSimParams) -> CentralCamera:
    """Return the simulated camera: its model, true intrinsics and distortion."""
    return p.camera()


def sim_target(p: ArmSimParams) -> Target:
    """Return the simulated target (a balloon has its own semi-axes)."""
    if p.target_kind == 'balloon':
        return make_target('balloon', axes=tuple(p.target_axes))
    return make_target(p.target_kind, p.target_radius)


def _pose(xyz_rpy) -> pin.SE3:
    return pose_from_xyz_rpy(xyz_rpy[:3], xyz_rpy[3:])


def sim_arm(p: ArmSimParams) -> ArmModel:
    """
    Return the simulated UR5: its URDF, hand-eye transform, target pose, limits, watchdog.

    ParameterError when the arm refuses them (``start_joints`` outside the URDF's joint
    limits: the elbow's are ±π, the parameter's bounds ±2π).
    """
    try:
        return _arm(p)
    except ValueError as exc:
        raise ParameterError(f'start_joints={list(p.start_joints)} or the arm parameters '
                             f'refused by the UR5 model: {exc}') from exc


def _arm(p: ArmSimParams) -> ArmModel:
    return ArmModel(
        urdf_path=p.urdf_path or None, tool0Mc=_pose(p.hand_eye), wMo=_pose(p.target_pose),
        q0=p.start_joints, damping=p.damping, singular_threshold=p.singular_threshold,
        singular_stop=p.singular_stop, velocity_scale=p.velocity_scale,
        cmd_timeout=p.cmd_timeout)


def sim_scene(p: ArmSimParams, arm: ArmModel | None = None) -> Scene:
    """
    Return the 3-D scene of the simulation: the arm, the target, the camera, ``desired_cMo``.

    ``arm``: the simulated arm (:func:`sim_arm` of ``p`` when None). SceneError when the
    URDF's meshes cannot be found.
    """
    return Scene(arm if arm is not None else sim_arm(p), sim_target(p), sim_camera(p),
                 _pose(p.desired_cMo))


class ArmSimCore:
    """The ``arm_sim`` node's logic (see the module docstring)."""

    def __init__(self, params: ArmSimParams):
        """Build the arm, the camera and the renderer; ParameterError if a pose is out of reach."""
        self.params = p = params
        self.camera = sim_camera(p)
        self.target = sim_target(p)
        self.renderer = Renderer(self.camera, self.target)
        self.dt = 1.0 / p.camera_rate
        self.lockstep = p.clock_mode == 'lockstep'
        self.arm = sim_arm(p)
        # the viewers' scene; without its meshes the simulation still runs (markers_error)
        self.scene: Scene | None = None
        self.markers_error = ''
        if p.markers_rate > 0:
            try:
                self.scene = sim_scene(p, self.arm)
            except SceneError as exc:
                self.markers_error = f'no markers: {exc}'
        self.path = CameraPath(max_points=PATH_POINTS)
        self._markers_t: float | None = None  # sim time of the last markers (None: due)
        q_start = self.named('start')  # raises if the IK fails: refused at start
        self.named('desired')
        self.arm.q_start = q_start
        self.arm.reset()
        self.waiting = self.lockstep  # re-publish the first frame until a command comes
        self._step_error = ''
        self._command_error = ''  # why the last command was refused
        self.held = False
        self.servo_enabled = False
        self.command_publishers: tuple[str, ...] = ()
        self._last_seq: int | None = None  # sequence number of the last executed command
        self._seq_t = 0.0                  # and its sim time

    def named(self, which: str) -> np.ndarray:
        """
        Return the joint configuration of the 'start' or 'desired' pose, by IK.

        From the current parameters; raises ParameterError if the IK does not converge or
        the camera would be inside the target (no camera can be there).
        """
        p = self.params
        try:  # a runtime start_joints within the parameter's ±2π, past the URDF's limits
            joints = self.arm.check_q(p.start_joints, 'start_joints')
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        if which == 'start' and p.start_mode == 'joints':
            q, what = joints, f'start_joints={list(p.start_joints)}'
        else:
            cMo = p.desired_cMo if which == 'desired' else p.start_cMo
            seed = joints if which == 'desired' else self.named('desired')
            q, ok, err = self.arm.ik_for_cMo(_pose(cMo), seed)
            if not ok:
                raise ParameterError(f'no UR5 configuration reaches {which}_cMo={list(cMo)} '
                                     f'(IK residual {err:.3g}); change it or target_pose')
            what = f'{which}_cMo={list(cMo)}'
        depth = self._inside_target(q)
        if depth <= 1.0:
            raise ParameterError(f'{what} puts the camera inside the target (at {depth:.3g} of '
                                 'its size from its centre): no camera can be there')
        return q

    def _inside_target(self, q) -> float:
        """
        Return where the camera is at ``q``, relative to the target's surface (≤ 1: inside).

        ``‖oc / axes‖`` with ``oc`` the camera centre in the target frame and ``axes`` the
        body's semi-axes (a sphere's radius on each): 1 on the surface.
        """
        axes = (np.full(3, self.target.radius) if self.target.axes is None
                else np.asarray(self.target.axes, dtype=float))
        return float(np.linalg.norm(self.arm.oMc(q).translation / axes))

    # --- command and time -----------------------------------------------------------
    def on_command(self, v_c, frame_id: str = CAMERA_FRAME, seq: int | None = None,
                   stamp_ns: int = 0) -> CommandOutcome:
        """
        Take a camera twist (6,) in frame ``frame_id``; in lockstep, step one period.

        A refused twist (:meth:`refusal`, or one the arm refuses: not finite, beyond its
        physical bound, or any in its error state) is not executed and stops the arm at
        once; in lockstep the period passes all the same with the arm held still, so the
        loop gets its image, unless it answers another frame than the last
        (:meth:`stale_answer`): that frame still waits for its own answer.
        ``seq``: the publisher's sequence number of the message (None or
        :data:`SEQ_UNSUPPORTED`: unknown, the one-driver rule is then the graph's warning).
        ``stamp_ns``: its header stamp (0: it answers no image).
        """
        v_c = np.asarray(v_c, dtype=float)
        seq = None if seq == SEQ_UNSUPPORTED else seq
        stale = self.stale_answer(stamp_ns)
        if stale:
            self.arm.stop()
            return CommandOutcome(False, reason=stale)
        reason = self.refusal(frame_id, seq)
        if reason:
            self.arm.stop()
        else:
            try:
                self.arm.command(v_c)
                self._last_seq, self._seq_t = seq, self.arm.t
            except TwistError as exc:  # the arm has stopped
                reason = str(exc)
        self._command_error = reason
        if not self.lockstep:
            return CommandOutcome(not reason, reason=reason)
        self.waiting = False
        return CommandOutcome(not reason, self.advance(), reason)

    def stale_answer(self, stamp_ns: int) -> str:
        """
        Return why a lockstep command stamped ``stamp_ns`` answers another frame ('' if not).

        A loop's twist carries the header of the image it answers; in lockstep one stamped
        with any time but the last frame's (0 aside: no image) was computed at another pose
        (before a jump, or in another run) and must neither move the arm nor step the clock.
        """
        now_ns = self.frame_stamp_ns
        if not self.lockstep or stamp_ns == 0 or stamp_ns == now_ns:
            return ''
        return (f'a command answering the image stamped {stamp_ns * 1e-9:.9f} s, not the '
                f'last one ({now_ns * 1e-9:.9f} s): computed at another pose, it steps nothing')

    @property
    def frame_stamp_ns(self) -> int:
        """Return the stamp of the frame shown now (the last one published)."""
        return int(round((START_TIME + self.arm.t) * 1e9))

    def refusal(self, frame_id: str, seq: int | None) -> str:
        """
        Return why a command is refused before the arm sees it ('' if it is not).

        Held (:meth:`hold`); another frame (:func:`frame_refusal`); or out
        of sequence: each publisher numbers its messages, so a number not above the last
        executed command's, while that command is fresh (``ArmModel.fresh``: the watchdog
        would still run it, ⌊cmd_timeout/dt⌋ periods after it), comes from a second
        publisher (or the same one restarted). Once the last command is older (its driver
        stopped), or one publisher is left (:meth:`on_command_publishers`), any may drive.
        """
        if self.held:
            return HELD
        reason = frame_refusal(frame_id)
        if reason or seq is None or self._last_seq is None:
            return reason
        if seq <= self._last_seq and self.arm.fresh(self._seq_t):
            names = ', '.join(self.command_publishers) or 'unknown'
            return (f'a command out of sequence (number {seq} after {self._last_seq}): from '
                    f'a second publisher (publishers: {names}); one driver at a time')
        return ''

    def on_command_publishers(self, names) -> None:
        """Take the command topic's publishers (node names); one left: it may drive."""
        self.command_publishers = tuple(names)
        if len(self.command_publishers) <= 1:
            self._last_seq = None

    def on_servo_enabled(self, enabled: bool) -> None:
        """Take whether a servo is enabled (jumps are refused while it is)."""
        self.servo_enabled = bool(enabled)

    def on_tick(self) -> SimFrame:
        """Step one period under the last command (realtime) and return the frame."""
        return self.advance()

    def advance(self) -> SimFrame:
        """Step one period; a step that fails holds the arm still (its error is reported)."""
        self._step_error = ''
        try:
            self.arm.step(self.dt)
        except Exception as e:  # noqa: BLE001 - never crash on a bad step; hold still
            self._step_error = str(e)
            self.arm.stop()
        return self.frame()

    @property
    def republish_due(self) -> bool:
        """Whether the last frame is to be re-published (module docstring: lockstep)."""
        return self.waiting or (self.lockstep and self.servo_enabled)

    # --- output ---------------------------------------------------------------------
    def frame(self) -> SimFrame:
        """Render the current state (a black image, and why, when rendering fails)."""
        cMo = self.arm.cMo()
        centre = (self.arm.wMo * cMo.inverse()).translation
        if np.all(np.isfinite(centre)):  # an invalid state is reported, not drawn
            self.path.add(centre)
        render_error = ''
        try:
            img = self.renderer.render(cMo)
        except Exception as e:  # noqa: BLE001 - a frame we cannot render: black, say why
            render_error = str(e)
            img = np.zeros((self.camera.height, self.camera.width, 3), np.uint8)
        return SimFrame(START_TIME + self.arm.t, img, cMo.inverse(),
                        tuple(self.arm.joint_names), self.arm.q.copy(), self.arm.qdot.copy(),
                        self.arm.info, render_error, self._step_error, self._command_error,
                        self.held, self.command_publishers)

    def markers(self, frame: SimFrame) -> list[MarkerSpec] | None:
        """
        Return the 3-D scene at ``frame`` when it is due, else None (module docstring).

        Never with ``markers_rate: 0`` or when the scene could not be built
        (:attr:`markers_error`). Link poses are the forward kinematics of ``frame.q``.
        """
        p = self.params
        if self.scene is None:
            return None
        if self._markers_t is not None and \
                frame.t - self._markers_t < 1.0 / p.markers_rate - 1e-9:
            return None
        self._markers_t = frame.t
        self.scene.set_desired(_pose(p.desired_cMo))  # a runtime parameter
        return self.scene.markers(frame.q, self.path.points, p.markers_mesh_uris)

    # --- jumps ----------------------------------------------------------------------
    def _jump(self, q, what: str) -> Jump:
        self.arm.set_q(q)
        self.arm.stop()
        self.path.clear()  # the path of a run starts where the arm jumped to
        self._markers_t = None
        self.arm.t += self.dt  # one period passes, so the new image has a new stamp
        self.waiting = self.lockstep
        self._step_error = ''
        frame = self.frame()
        # a jump moves the arm but clears neither the error nor the hold: say so
        note = (' (the arm is in error: commands are refused until ~/reset)'
                if self.arm.error is not None else
                ' (held: commands are refused until ~/release)' if self.held else '')
        # the stamp ends the reply, so a caller knows which images show the new pose
        return Jump(True, f'at {what}{note}: q={np.round(q, 4).tolist()}, first image '
                    f'stamped {frame.t:.9f}', frame)

    def reset(self) -> Jump:
        """
        Go back to the start configuration, at rest, watchdog re-armed (time kept).

        It clears the error state and releases the hold; refused while a servo is enabled.
        """
        if self.servo_enabled:
            return Jump(False, SERVO_ENABLED)
        t = self.arm.t
        self.arm.reset()
        self.arm.t = t
        self.held, self._last_seq = False, None
        return self._jump(self.arm.q_start, 'start (reset)')

    def go(self, which: str) -> Jump:
        """
        Jump to the 'start' or 'desired' configuration of the current parameters.

        Refused while a servo is enabled, when the IK does not reach the pose, or when it
        puts the camera inside the target.
        """
        if self.servo_enabled:
            return Jump(False, SERVO_ENABLED)
        try:
            q = self.named(which)
        except ParameterError as e:
            return Jump(False, str(e))
        return self._jump(q, which)

    def hold(self) -> Jump:
        """Drop the current command (the arm stops at the next step) and latch: see HELD."""
        self.arm.stop()
        self.held = True
        return Jump(True, 'command dropped')

    def release(self) -> Jump:
        """Release the hold: commands are executed again (the next one moves the arm)."""
        was, self.held = self.held, False
        if self.arm.error is not None:  # the hold is gone, but commands are still refused
            return Jump(True, f'{"released" if was else "not held"}, but the arm is in '
                        f'error ({self.arm.error}): commands are refused until ~/reset')
        return Jump(True, 'released: commands are executed again' if was else
                    'not held: nothing to release')
