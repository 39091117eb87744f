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
  loop never stalls). The first frame, and the one after a jump, is *re-published* unchanged (same
  stamp) until the next command arrives (:attr:`ArmSimCore.waiting`), so a subscriber that
  connects late still gets it.

Commands are camera twists in :data:`~sphere_servo.sim.arm.CAMERA_FRAME` (the current
camera optical frame); one that is not finite, or is in another frame, is refused and not
executed: in realtime the last valid command stays (until the watchdog), in lockstep the
period passes with the arm held still.

Jumps (the node's services): ``reset`` (start configuration, at rest, watchdog re-armed,
sim time kept), ``go_start`` / ``go_desired`` (the IK of ``start_cMo`` / ``desired_cMo``,
from the parameters as they are now), ``hold`` (drop the command). A jump lets one period
pass, so the new image has a new stamp, which ends the reply.
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
from sphere_servo.vision.renderer import Renderer

START_TIME = 1.0  # s; stamp 0 means "unset" to many ROS tools
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

    @property
    def stamp_ns(self) -> int:
        """Return the stamp of every message of the frame."""
        return int(round(self.t * 1e9))

    @property
    def level(self) -> Level:
        """
        Return how serious the frame's status is.

        ERROR when the step or the render failed; WARN at a limit, near a singularity, on a
        timeout, or after a refused command; OK else.
        """
        if self.step_error or self.render_error:
            return Level.ERROR
        return max(LEVELS[self.info.status], Level.WARN if self.command_error else Level.OK)

    def status_values(self) -> dict[str, str]:
        """Return the status values, key → text, in the published order."""
        st = self.info
        v = {'joints': ','.join(st.joints), 'sigma_min': f'{st.sigma_min:.5f}',
             'scale': f'{st.scale:.4f}', 'sim_time': f'{self.t:.6f}', 'detail': st.message}
        for key, text in (('command_error', self.command_error),
                          ('step_error', self.step_error), ('render_error', self.render_error)):
            if text:
                v[key] = text
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


def command_refusal(v_c: np.ndarray, frame_id: str) -> str:
    """Return why a camera twist ``v_c`` in frame ``frame_id`` is refused ('' if it is not)."""
    if frame_id != CAMERA_FRAME:
        return (f'a camera twist in frame {frame_id!r}: arm_sim takes twists in '
                f'{CAMERA_FRAME!r} only')
    if v_c.shape != (6,) or not np.all(np.isfinite(v_c)):
        return f'a non-finite camera twist {v_c.ravel().tolist()}'
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
        self.arm = ArmModel(
            urdf_path=p.urdf_path or None, tool0Mc=_pose(p.hand_eye), wMo=_pose(p.target_pose),
            q0=p.start_joints, damping=p.damping, singular_threshold=p.singular_threshold,
            singular_stop=p.singular_stop, velocity_scale=p.velocity_scale,
            cmd_timeout=p.cmd_timeout)
        q_start = self.named('start')  # raises if the IK fails: refused at start
        self.named('desired')
        self.arm.q_start = q_start
        self.arm.reset()
        self.waiting = self.lockstep  # re-publish the first frame until a command comes
        self._step_error = ''
        self._command_error = ''  # why the last command was refused

    def named(self, which: str) -> np.ndarray:
        """
        Return the joint configuration of the 'start' or 'desired' pose, by IK.

        From the current parameters; raises ParameterError if the IK does not converge.
        """
        p = self.params
        if which == 'start' and p.start_mode == 'joints':
            return np.asarray(p.start_joints, dtype=float)
        cMo = p.desired_cMo if which == 'desired' else p.start_cMo
        seed = p.start_joints if which == 'desired' else self.named('desired')
        q, ok, err = self.arm.ik_for_cMo(_pose(cMo), seed)
        if not ok:
            raise ParameterError(f'no UR5 configuration reaches {which}_cMo={list(cMo)} '
                                 f'(IK residual {err:.3g}); change it or target_pose')
        return q

    # --- command and time -----------------------------------------------------------
    def on_command(self, v_c, frame_id: str = CAMERA_FRAME) -> CommandOutcome:
        """
        Take a camera twist (6,) in frame ``frame_id``; in lockstep, step one period.

        A refused twist (:func:`command_refusal`, or one the arm refuses: beyond its
        physical bound) is not executed and stops the arm at once; in lockstep the period
        passes all the same with the arm held still, so the loop gets its image.
        """
        v_c = np.asarray(v_c, dtype=float)
        reason = command_refusal(v_c, frame_id)
        if reason:
            self.arm.stop()
        else:
            try:
                self.arm.command(v_c)
            except TwistError as exc:  # the arm has stopped
                reason = str(exc)
        self._command_error = reason
        if not self.lockstep:
            return CommandOutcome(not reason, reason=reason)
        self.waiting = False
        return CommandOutcome(not reason, self.advance(), reason)

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
        """Whether the last frame is to be re-published (lockstep, no command since)."""
        return self.waiting

    # --- output ---------------------------------------------------------------------
    def frame(self) -> SimFrame:
        """Render the current state (a black image, and why, when rendering fails)."""
        cMo = self.arm.cMo()
        render_error = ''
        try:
            img = self.renderer.render(cMo)
        except Exception as e:  # noqa: BLE001 - a frame we cannot render: black, say why
            render_error = str(e)
            img = np.zeros((self.camera.height, self.camera.width, 3), np.uint8)
        return SimFrame(START_TIME + self.arm.t, img, cMo.inverse(),
                        tuple(self.arm.joint_names), self.arm.q.copy(), self.arm.qdot.copy(),
                        self.arm.info, render_error, self._step_error, self._command_error)

    # --- jumps ----------------------------------------------------------------------
    def _jump(self, q, what: str) -> Jump:
        self.arm.set_q(q)
        self.arm.stop()
        self.arm.t += self.dt  # one period passes, so the new image has a new stamp
        self.waiting = self.lockstep
        self._step_error = ''
        frame = self.frame()
        # the stamp ends the reply, so a caller knows which images show the new pose
        return Jump(True, f'at {what}: q={np.round(q, 4).tolist()}, first image stamped '
                    f'{frame.t:.9f}', frame)

    def reset(self) -> Jump:
        """Go back to the start configuration, at rest, watchdog re-armed (time kept)."""
        t = self.arm.t
        self.arm.reset()
        self.arm.t = t
        return self._jump(self.arm.q_start, 'start (reset)')

    def go(self, which: str) -> Jump:
        """Jump to the 'start' or 'desired' configuration of the current parameters."""
        try:
            q = self.named(which)
        except ParameterError as e:
            return Jump(False, str(e))
        return self._jump(q, which)

    def hold(self) -> Jump:
        """Drop the current command (the arm stops at the next step)."""
        self.arm.stop()
        return Jump(True, 'command dropped')
