"""The obstacle stage on frames built by the OAK driver's host-side conversion from real depthai
ImgFrame messages (RAW16 disparity with 3 fractional bits, as the device sends it; baseline and
intrinsics in Frame.meta as the driver reports its EEPROM calibration). No device needed."""
from __future__ import annotations

from datetime import timedelta

import numpy as np
import pytest

from conftest import import_extra
dai = import_extra("depthai", "oak")  # CI installs the extra: there a missing depthai fails

import disparity_scenes as ds  # noqa: E402

from vbnav.control.config import parse_config  # noqa: E402
from vbnav.control.stages.obstacles import make_obstacle_stage  # noqa: E402
from vbnav.drivers.oak_camera import frame_from_imgframes  # noqa: E402
from vbnav.vision.geometry import Pose2  # noqa: E402
from vbnav.vision.obstacles import PixelClass  # noqa: E402
from vbnav.vision.camera_model import PinholeCamera  # noqa: E402
from vbnav.vision.stereo import StereoRig  # noqa: E402

RIG = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
K = [[400.0, 0.0, 319.5], [0.0, 400.0, 239.5], [0.0, 0.0, 1.0]]


def oak_frame(scene: ds.Scene, seq: int):
    r = ds.render(scene, RIG)
    img = dai.ImgFrame()
    img.setCvFrame(np.full((480, 640), 128, np.uint8), dai.ImgFrame.Type.GRAY8)
    img.setSequenceNum(seq)
    img.setTimestamp(timedelta(milliseconds=66.7 * seq))
    raw = np.round(np.nan_to_num(r.disparity) * 8).astype(np.uint16)        # subpixel, 3 fractional bits
    d = dai.ImgFrame()
    d.setFrame(raw)
    d.setType(dai.ImgFrame.Type.RAW16)
    d.setWidth(640)
    d.setHeight(480)
    d.setSequenceNum(seq)
    frame = frame_from_imgframes(img, d, seq=seq, subpixel_bits=3, meta={"baseline_m": 0.075, "K": K})
    return frame, r


def test_oak_disparity_frames_drive_the_stop_zone():
    cfg = parse_config({"camera": {"driver": "oak"},
                        "obstacles": {"enabled": True, "obstacle_height": 0.01, "noise_px": 0.15,
                                      "persist_k": 2, "persist_n": 3}})
    stage = make_obstacle_stage(cfg)            # no baseline in the config: it comes with the frames
    far = ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.15, 0.15, 3.0, 3.15, 0.02),))      # 2 cm box 3 m ahead
    near = ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.15, 0.15, 0.6, 0.75, 0.02),))     # in the stop band
    stage.keep_labels = True
    frame, r = oak_frame(far, 1)
    e = stage.process(frame, Pose2())
    assert e.ok and e.info["speed_scale"] == 1.0
    box = r.surface == ds.BOX0
    assert np.mean(e.value.labels[box] == PixelClass.OBSTACLE) >= 0.95
    # measured 2.3e-4 on 2026-12-04, bar 2x
    assert np.mean(e.value.labels[r.surface == ds.FLOOR] == PixelClass.OBSTACLE) <= 5e-4
    assert e.value.nearest[0] == pytest.approx(3.1, abs=0.05)          # 3.0 m + the camera's 0.1 m
    scales = [stage.process(oak_frame(near, s)[0], Pose2()).info["speed_scale"] for s in (2, 3)]
    assert scales == [1.0, 0.0]                 # 2 of 3 frames: stopped on the second
