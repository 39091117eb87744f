"""The Monte Carlo study: resumable, seeded, and its table comes from the runs (tiny N)."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import cc_target
from sphere_servo.experiments import study


def test_start_poses_are_seeded_and_in_view():
    a, b = study.start_poses(5, seed=3), study.start_poses(5, seed=3)
    cam = CameraIntrinsics()
    for p, q in zip(a, b):
        assert np.allclose(p.homogeneous, q.homogeneous)
        obs = observe(p, cc_target())
        assert np.all(cam.in_image(cam.project(np.array([obs.sphere.b, *obs.q.values()]))))
        t = cc_target()
        cP1, n_c = p.act(t.marks()['P1']), p.rotation @ t.surface_normal(t.marks()['P1'])
        assert np.degrees(np.arccos(-(n_c @ cP1) / np.linalg.norm(cP1))) <= 80.0


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


def _task(cond, fs, idx, poses):
    return (cond, fs, idx, poses[idx].homogeneous.tolist())


def test_noise_runs_are_judged_on_their_steady_state():
    """Under pixel noise the run goes the whole horizon; success is the mean pose over the
    last window, and the scatter about it is reported (it is not zero: the noise is real)."""
    poses = study.start_poses(3, seed=0)
    row = study.run_cell(_task('noise', 's_n', 0, poses))
    assert row['iterations'] < study.NOISY_ITER and row['reason'] == 'max_iter'
    assert row['success'] and row['bias_mm'] < 5.0 and row['bias_deg'] < 1.0
    assert 0.1 < row['jitter_mm'] < 20.0 and 0.01 < row['jitter_deg'] < 3.0
    ideal = study.run_cell(_task('ideal', 's_n', 0, poses))
    assert ideal['success'] and 'jitter_mm' not in ideal


def test_arm_condition_counts_joint_limit_hits_and_leaves_out_unreachable_starts():
    """The UR5 in the loop with the cell's safety limit (the paper scenario's elbow limit):
    s_cc's detour meets it from two of these starts where s_n converges; a start the arm
    cannot reach inside its limits is left out, not counted as a failure."""
    poses = study.start_poses(5, seed=0)
    rows = [study.run_cell(_task('arm', fs, i, poses)) for i in range(5) for fs in ('s_n', 's_cc')]
    reach = [r for r in rows if not r.get('excluded')]
    assert reach and len(reach) < len(rows)      # start 2 is out of the UR5's reach
    assert all(r['success'] for r in reach if r['set'] == 's_n')
    cell, _ = study.cell_limit()
    hits = [r for r in reach if r['joint_limit']]
    assert len(hits) == 2 and all(r['set'] == 's_cc' and r['reason'] == f'joint_limit: {cell}'
                                  for r in hits), hits
    s = study.summarize(rows)
    assert s[('arm', 's_n')]['n'] == len(reach) // 2 and s[('arm', 's_n')]['joint_limit'] == 0
    assert s[('arm', 's_cc')]['joint_limit'] == pytest.approx(100 * 2 / (len(reach) // 2))


def test_arm_run_ends_where_a_singularity_stops_the_arm():
    """ibvs's camera retreat stretches the UR5 out until the arm node stops it at its
    singularity threshold: the run ends there with that reason (it used to wait, unmoving,
    for max_iter)."""
    from sphere_servo.experiments.scenarios import CMO_DESIRED
    from sphere_servo.experiments import paper
    poses = study.start_poses(20, seed=0)
    res = paper.run_arm(cc_target(), poses[19], CMO_DESIRED, 'ibvs', gain=study.ADAPTIVE,
                        max_iter=study.MAX_ITER, arm=paper.make_arm(paper.JL_CELL_LIMITS),
                        camera=study.CAM)
    assert res.reason == paper.SINGULAR_STOP and res.iterations < 50, (res.reason,
                                                                        res.iterations)
    assert res.arm_status[-1] == 'singularity'
    row = study.run_cell(_task('arm', 'ibvs', 19, poses))
    assert row['reason'] == paper.SINGULAR_STOP and not row['success']
