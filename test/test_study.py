"""The Monte Carlo study: resumable, seeded, and its table comes from the runs (tiny N)."""
from __future__ import annotations

import io
import json

import numpy as np

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import cc_target
from sphere_servo.tools import study


def test_start_poses_are_seeded_and_in_view():
    a, b = study.start_poses(5, seed=3), study.start_poses(5, seed=3)
    cam = CameraIntrinsics()
    for p, q in zip(a, b):
        assert np.allclose(p.homogeneous, q.homogeneous)
        obs = observe(p, cc_target())
        assert np.all(cam.in_image(cam.project(np.array([obs.sphere.b, *obs.q.values()]))))


def test_run_resume_and_report(tmp_path, monkeypatch):
    monkeypatch.setattr(study, 'CONDITIONS', ('ideal', 'balloon'))
    rows = study.run_study(2, 0, tmp_path, workers=1, log=io.StringIO())
    assert len(rows) == 2 * 4 + 2 * 3          # no s_cc on the balloon
    lines = (tmp_path / 'runs.jsonl').read_text().splitlines()
    assert len(lines) == len(rows)
    log = io.StringIO()
    again = study.run_study(2, 0, tmp_path, resume=True, workers=1, log=log)
    assert '0 to go' in log.getvalue() and len(again) == len(rows)
    s = study.summarize(rows)
    assert s[('ideal', 's_n')]['success'] == 100.0
    rep = study.write_report(rows, tmp_path, 2, 0, None, 1).read_text()
    assert '| ideal | s_n | 2 | 100.0 % |' in rep
    assert (tmp_path / 'study.png').exists()
    assert all(json.loads(x)['cond'] in ('ideal', 'balloon') for x in lines)
