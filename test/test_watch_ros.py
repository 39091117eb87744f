"""
Test the video and the replay page on a real run: ``make demo``'s scenario over ROS 2.

The launcher runs the lockstep special-sphere scenario (four nodes over DDS) and records
the bag (``test_refeatures``'s ``lockstep_run``); the video and the replay page are made
from it. What is checked comes from the
run itself: the servo's own iteration count in its ``servo/state`` messages, the image the
launcher says it taught, and the pixels of the decoded video.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

pytest.importorskip('rclpy')
from rosbags.highlevel import AnyReader  # noqa: E402

from sphere_servo.bag import bagio  # noqa: E402
from sphere_servo.bag.run import read_run  # noqa: E402
from sphere_servo.experiments import replay3d, video  # noqa: E402
from test_refeatures import lockstep_run  # noqa: E402, F401 - the recorded run
from test_replay3d import _commands  # noqa: E402
from test_video import _decode, goal_ring, sphere_centre  # noqa: E402


def _servo_iterations(bag) -> tuple[int, int]:
    """
    Count the servo's iterations by its own ``servo/state`` messages (DiagnosticArray).

    Returns the distinct images it answered while enabled (the ``stamp`` value) and its last
    ``iteration`` value.
    """
    with AnyReader([bag], default_typestore=bagio.typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == '/servo/state']
        stamps, last = set(), 0
        for c, _, raw in reader.messages(connections=conns):
            st = reader.deserialize(raw, c.msgtype).status[0]
            vals = {kv.key: kv.value for kv in st.values}
            if st.message in ('servoing', 'converged', 'target lost', 'no desired') \
                    and 'stamp' in vals:
                stamps.add(vals['stamp'])
                last = int(vals['iteration'])
    return len(stamps), last


def test_video_and_replay_of_a_ros_run(lockstep_run, tmp_path):  # noqa: F811
    bag, _, taught = lockstep_run
    run = read_run(bag)
    assert run.desired.how == 'taught' and run.desired.stamp == taught
    out = tmp_path / 'servo.mp4'
    assert video.main([str(bag), '-o', str(out), '--quiet']) == 0
    frames = _decode(out)
    answered, iterations = _servo_iterations(bag)
    assert len(frames) == answered == iterations > 50
    cams = [f[:480, :640] for f in frames]
    ring0, d0 = goal_ring(cams[0])
    ring1, _ = goal_ring(cams[-1])
    assert np.linalg.norm(sphere_centre(cams[0]) - ring0) > 0.5 * d0
    assert np.linalg.norm(sphere_centre(cams[-1]) - ring1) < 2.0
    page = tmp_path / 'replay.html'
    # the config the run used: the bag's ground truth agrees with its arm
    assert replay3d.main([str(bag), '-o', str(page)]) == 0
    cmds = _commands(page.read_text(encoding='utf-8'))
    anim = [c for c in cmds if c['type'] == 'set_animation'][0]
    keys = {a['path']: [k['time'] for k in a['clip']['tracks'][0]['keys']]
            for a in anim['animations']}
    # a key for each frame whose joint state the recorder got, at its frame number
    posed = [k for k, st in enumerate(run.frames) if st in run.joints]
    assert keys['/meshcat/camera/0'] == posed and len(run.frames) == len(frames)
    assert len(posed) > 0.5 * len(frames)
    assert cv2.VideoCapture(str(out)).get(cv2.CAP_PROP_FPS) == pytest.approx(30.0, abs=0.1)
