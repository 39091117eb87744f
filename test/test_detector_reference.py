"""
The detector's results are pinned: every frame of a fixed corpus gives the recorded Detection.

The corpus (test/detector_corpus.py: textures, distractors, far, grazing, cut, camera
models, encodings, wrong intrinsics) and its reference file were recorded with the detector
before its speed work; any change of a result — found or not, why, the conic, the sphere,
the ellipse, a mark's pixel, ray, area or reason — beyond 1e-9 relative fails here.
"""
from __future__ import annotations

import copy

from detector_corpus import cases, differences, image_hash, load_reference, record


def test_every_corpus_frame_gives_the_recorded_detection():
    ref = load_reference()
    seen, changed, moved = set(), [], []
    for name, make, img, enc, cam in cases():
        seen.add(name)
        assert name in ref, f'{name} is not in the reference file (regenerate it)'
        if image_hash(img) != ref[name]['image']:
            moved.append(name)      # the renderer changed the corpus, not the detector
            continue
        diff = differences(ref[name]['detection'], record(make().detect(img, enc, cam)))
        if diff:
            changed.append(f'{name}: ' + '; '.join(diff[:4]))
    assert not moved, f'corpus images differ from the recorded ones: {moved}'
    assert seen == set(ref), f'reference frames not in the corpus: {sorted(set(ref) - seen)}'
    assert len(seen) >= 140
    assert not changed, f'{len(changed)} detections changed:\n' + '\n'.join(changed)


def _bumped(rec: dict, path: tuple, by):
    """Return a copy of ``rec`` with the value at ``path`` (keys, then an index) changed."""
    out = copy.deepcopy(rec)
    *keys, last = path
    node = out
    for k in keys:
        node = node[k]
    node[last] = by(node[last])
    return out


def test_the_comparison_sees_a_change_of_any_field():
    ref = load_reference()
    name = next(k for k, v in ref.items() if v['detection']['found']
                and all(m['visible'] for m in v['detection']['marks'].values()))
    want = ref[name]['detection']
    assert differences(want, copy.deepcopy(want)) == []
    for path, by in ((('sphere', 'r_delta'), lambda x: x * (1 + 1e-8)),
                     (('sphere', 'b', 2), lambda x: x * (1 + 1e-8)),
                     (('conic', 8), lambda x: x + 1e-8),          # a unit-norm conic
                     (('ellipse_px', 'angle_deg'), lambda x: x + 1e-6),
                     (('marks', 'P1', 'ray', 0), lambda x: x + 1e-8),
                     (('marks', 'P2', 'area_px'), lambda x: x * (1 + 1e-8)),
                     (('marks', 'P2', 'visible'), lambda x: not x),
                     (('n_edge_points',), lambda x: x - 1),
                     (('reason',), lambda x: x + 'x')):
        assert differences(want, _bumped(want, path, by)), path
