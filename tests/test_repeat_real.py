"""Teach-and-repeat on real images (issue 13, point 5): KITTI 06 taught on the left camera, repeated on the right.

The right camera sees the route from a true lateral offset of 0.537 m (the stereo baseline) at heading
0. The repeat runs the real stages on the replay camera's frames, native resolution (1226x370, fx 707):
TeachStage on the left images with the ground-truth poses as planar odometry (the only metric input:
every taught inverse height gets its scale from it), then RepeatStage.process on the right images,
from the first frame and starting 1-3 frames further along the route. The mounting pitch is the
camera's tilt against its direction of travel (1.22 deg, kitti_util.mount_pitch_from_travel).

Bars (measured on 2026-11-30, shifts 0-3; the issue asks <= 20 mm and 0.3 deg):
- median lateral error 7.6-9.6 mm then, 12.6-15.5 mm re-measured on 2026-12-01 (p95 47-172 mm: the
  first keyframes have few near landmarks); bar 18 mm, about 2x the worst shift then. Expected scale: 1 px at f = 707 is 1.4 mrad; landmarks at
  ~10 m carry the lateral offset, so one match is worth ~14 mm and ~100 of them a few mm; taught
  inverse heights good to ~5-10 % each add little once averaged.
- median heading error 0.032-0.039 deg, bar 0.08 deg (2x); p95 0.13-0.25 deg, bar 0.5 deg (2x).
- the chosen keyframe right on every frame (kitti_util.right_keyframes: the first keyframe ahead, or
  either neighbour within 10 % of the keyframe spacing of one), the last frame on the last keyframe,
  and the fix trusted on >= 90 % of frames (measured 48-50 of 48-51).
"""
from __future__ import annotations

import numpy as np
import pytest

from kitti_util import repeat_right, teach_kitti

SHIFTS = (0, 1, 2, 3)
LATERAL_MEDIAN_M = 0.018
HEADING_MEDIAN_DEG = 0.08
HEADING_P95_DEG = 0.5


@pytest.fixture(scope="module")
def runs(shared_data):
    taught = teach_kitti(shared_data / "kitti06_stereo")
    out = {s: repeat_right(taught, s) for s in SHIFTS}
    for s, r in out.items():
        print(f"shift {s}: fixes ok {r.ok.sum()}/{len(r.ok)}, lateral median {1e3 * np.median(r.lateral_err):.1f} mm "
              f"p95 {1e3 * np.percentile(r.lateral_err, 95):.1f} mm, heading median {np.median(r.heading_err):.3f} "
              f"p95 {np.percentile(r.heading_err, 95):.3f} deg, keyframe right {r.keyframe_right.sum()}/{len(r.ok)}")
    return taught, out


@pytest.mark.realdata
@pytest.mark.parametrize("shift", SHIFTS)
def test_repeat_on_the_right_images_recovers_the_stereo_baseline(runs, shift):
    taught, out = runs
    r = out[shift]
    assert abs(taught.baseline - 0.537) < 0.001
    assert r.ok.mean() >= 0.9, f"only {r.ok.sum()} of {len(r.ok)} fixes trusted"
    assert np.median(r.lateral_err) <= LATERAL_MEDIAN_M
    assert np.median(r.heading_err) <= HEADING_MEDIAN_DEG
    assert np.percentile(r.heading_err, 95) <= HEADING_P95_DEG


@pytest.mark.realdata
@pytest.mark.parametrize("shift", SHIFTS)
def test_repeat_on_the_right_images_localises_against_the_right_keyframe(runs, shift):
    taught, out = runs
    r = out[shift]
    wrong = r.index[~r.keyframe_right]
    assert not len(wrong), f"wrong keyframe at frames {wrong.tolist()} (chose {r.keyframe[~r.keyframe_right].tolist()})"
    assert r.keyframe[-1] == len(taught.route.keyframes) - 1        # reached the end of the route
