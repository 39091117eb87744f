"""The Monte Carlo study: resumable, seeded, and its table comes from the runs (tiny N)."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from sphere_servo.core.camera import CameraIntrinsics
from sphere_servo.core.measurement import observe
from sphere_servo.core.targets import cc_target
from sphere_servo.experiments import study, study_cells, study_report
from sphere_servo.experiments.arm_cell import make_arm, run_arm
from sphere_servo.experiments.ibvs import IbvsFeatures
from sphere_servo.experiments.scenarios import CMO_DESIRED, JL_CELL_LIMITS
from sphere_servo.sim.arm import Status
from sphere_servo.sim.loop import LoopOutcome
from sphere_servo.sim.plants import SINGULAR_DETAIL


def test_start_poses_are_seeded_and_in_view():
    a, b = study_cells.start_poses(5, seed=3), study_cells.start_poses(5, seed=3)
    cam = CameraIntrinsics()
    for p, q in zip(a, b):
        assert np.allclose(p.homogeneous, q.homogeneous)
        obs = observe(p, cc_target())
        assert np.all(cam.in_image(cam.project(np.array([obs.sphere.b, *obs.q.values()]))))
        t = cc_target()
        cP1, n_c = p.act(t.marks()['P1']), p.rotation @ t.surface_normal(t.marks()['P1'])
        assert np.degrees(np.arccos(-(n_c @ cP1) / np.linalg.norm(cP1))) <= 80.0


def test_run_resume_and_report(tmp_path, monkeypatch):
    monkeypatch.setattr(study_cells, 'CONDITIONS', ('ideal', 'balloon'))
    rows = study.run_study(2, 0, tmp_path, workers=1, log=io.StringIO())
    assert len(rows) == 2 * 4 + 2 * 3          # no s_cc on the balloon
    lines = (tmp_path / 'runs.jsonl').read_text().splitlines()
    assert len(lines) == len(rows)
    log = io.StringIO()
    again = study.run_study(2, 0, tmp_path, resume=True, workers=1, log=log)
    assert '0 to go' in log.getvalue() and len(again) == len(rows)
    s = study_report.summarize(rows)
    assert s[('ideal', 's_n')]['success'] == 100.0
    rep = study_report.write_report(rows, tmp_path, 2, 0, None, 1).read_text()
    assert '| ideal | s_n | 2 | 100.0 % |' in rep
    assert (tmp_path / 'study.png').exists()
    assert all(json.loads(x)['cond'] in ('ideal', 'balloon') for x in lines)


def _task(cond, fs, idx, poses):
    return (cond, fs, idx, poses[idx].homogeneous.tolist())


def test_noise_runs_are_judged_on_their_steady_state():
    """
    Under pixel noise the run goes the whole horizon.

    Success is the mean pose over the last window, and the scatter about it is reported (it
    is not zero: the noise is real).
    """
    poses = study_cells.start_poses(3, seed=0)
    row = study_cells.run_cell(_task('noise', 's_n', 0, poses))
    assert row['iterations'] < study_cells.NOISY_ITER
    assert row['reason'] == LoopOutcome.MAX_ITER.value
    assert row['success'] and row['bias_mm'] < 5.0 and row['bias_deg'] < 1.0
    assert 0.1 < row['jitter_mm'] < 20.0 and 0.01 < row['jitter_deg'] < 3.0
    ideal = study_cells.run_cell(_task('ideal', 's_n', 0, poses))
    assert ideal['success'] and 'jitter_mm' not in ideal


def test_arm_condition_counts_joint_limit_hits_and_leaves_out_unreachable_starts():
    """
    The UR5 in the loop with the cell's safety limit (the paper scenario's elbow limit).

    s_cc's detour meets it from two of these starts where s_n converges; a start the arm
    cannot reach inside its limits is left out, not counted as a failure.
    """
    poses = study_cells.start_poses(5, seed=0)
    rows = [study_cells.run_cell(_task('arm', fs, i, poses)) for i in range(5)
            for fs in ('s_n', 's_cc')]
    reach = [r for r in rows if not r.get('excluded')]
    assert reach and len(reach) < len(rows)      # start 2 is out of the UR5's reach
    assert all(r['success'] for r in reach if r['set'] == 's_n')
    cell, _ = study_report.cell_limit()
    hits = [r for r in reach if r['joint_limit']]
    assert len(hits) == 2 and all(r['set'] == 's_cc' and r['reason'] == f'joint_limit: {cell}'
                                  for r in hits), hits
    s = study_report.summarize(rows)
    assert s[('arm', 's_n')]['n'] == len(reach) // 2 and s[('arm', 's_n')]['joint_limit'] == 0
    assert s[('arm', 's_cc')]['joint_limit'] == pytest.approx(100 * 2 / (len(reach) // 2))


def test_arm_run_ends_where_a_singularity_stops_the_arm():
    """
    The IBVS camera retreat stretches the UR5 out until the arm stops near a singularity.

    The arm node stops it at its singularity threshold: the run ends there with that
    outcome instead of waiting, unmoving, for max_iter.
    """
    poses = study_cells.start_poses(20, seed=0)
    res = run_arm(cc_target(), poses[19], CMO_DESIRED, IbvsFeatures, gain=study_cells.ADAPTIVE,
                  max_iter=study_cells.MAX_ITER, arm=make_arm(JL_CELL_LIMITS),
                  camera=study_cells.CAM)
    assert res.outcome is LoopOutcome.SINGULARITY, res.reason
    assert res.iterations < 50, res.iterations
    assert res.detail == SINGULAR_DETAIL
    assert res.arm_status[-1] is Status.SINGULARITY
    row = study_cells.run_cell(_task('arm', 'ibvs', 19, poses))
    assert row['reason'] == res.reason and not row['success']
    assert row['reason'] == 'singularity: the arm stopped near a singular configuration'


def test_camera_conditions_see_what_each_camera_sees():
    """
    The same starts through each camera: what leaves a pinhole's image stays in a fisheye's.

    From the pinhole's starts, the runs of ``s`` whose target leaves the pinhole's image
    succeed through the fisheye with the target in view all along; the wide starts are in
    both wide images, some far outside the pinhole's view (not in view at the start, no
    run), where the fisheye's s_n run converges.
    """
    poses = study_cells.start_poses(6, seed=0)
    rows = [study_cells.run_cell(_task('ideal', 's', i, poses)) for i in range(6)]
    left = [r['idx'] for r in rows if r['converged'] and r['left_image']]
    assert left, 'no pinhole start of s leaves the image: pick another seed'
    for i in left:
        r = study_cells.run_cell(_task('fisheye', 's', i, poses))
        assert r['success'] and not r['left_image'], r
    wide = study_cells.wide_start_poses(6, seed=0)
    cams = [study_cells.camera('fisheye'), study_cells.camera('catadioptric')]
    unseen = []
    for i, p in enumerate(wide):
        obs = observe(p, cc_target(), max_angle=min(c.max_angle for c in cams))
        rays = np.array([obs.sphere.b, *obs.q.values()])
        assert all(np.all(c.in_view(rays, margin=20.0)) for c in cams)
        if not np.all(study_cells.CAM.in_view(rays)):
            unseen.append(i)
    assert unseen
    r = study_cells.run_cell(_task('pinhole_wide', 's_n', unseen[0], wide))
    assert not r['success'] and r['reason'] == study_cells.NOT_IN_VIEW and r['iterations'] == 0
    r = study_cells.run_cell(_task('fisheye_wide', 's_n', unseen[0], wide))
    assert r['success'], r
