"""ReplayCamera over folders, KITTI and TUM layouts, on the simulated clock."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from pydantic import ValidationError

from vbnav.drivers.camera import CameraError
from vbnav.drivers.clock import SimClock
from vbnav.drivers.registry import CAMERAS, load
from vbnav.drivers.replay_camera import ReplayCamera

S = 1_000_000_000


def write_folder(path, n, rng):
    path.mkdir(parents=True, exist_ok=True)
    imgs = []
    for i in range(n):
        img = rng.integers(0, 255, (24, 32), dtype=np.uint8)
        cv2.imwrite(str(path / f"{i:06d}.png"), img)
        imgs.append(img)
    return imgs


def test_registry_name_resolves_and_options_are_strict():
    assert load(CAMERAS, "replay") is ReplayCamera
    with pytest.raises(ValidationError, match="rate"):
        ReplayCamera.Options(path="x", rate=3)
    with pytest.raises(ValidationError):
        ReplayCamera.Options(path="x", rate_hz=-1)


def test_folder_replay_at_a_fixed_rate_drops_late_frames_and_loops(tmp_path, rng):
    imgs = write_folder(tmp_path / "seq", 5, rng)
    clock = SimClock()
    with ReplayCamera({"path": str(tmp_path / "seq"), "rate_hz": 20.0, "loop": True}, clock) as cam:
        f0 = cam.read()
        assert f0.meta["index"] == 0 and np.array_equal(f0.image, imgs[0])
        assert cam.read() is None  # frame 1 is not due yet
        f1 = cam.read(timeout_s=1.0)  # sleeps (on the simulated clock) until frame 1 is due
        assert f1.meta["index"] == 1 and f1.stamp_ns - f0.stamp_ns == S // 20
        clock.advance(3 * S // 20)  # frames 2, 3 and 4 fall due; a live camera gives the latest
        f = cam.read()
        assert f.meta["index"] == 4 and f.meta["dropped"] == 2 and f.seq == 3
        f = cam.read(timeout_s=1.0)
        assert f.meta["index"] == 0 and f.meta["lap"] == 1  # looped, one period after the last frame


def test_kitti_replay_at_recorded_rate_gives_stereo_pairs(tmp_path, rng):
    root = tmp_path / "kitti"
    write_folder(root / "image_l", 3, rng)
    write_folder(root / "image_r", 3, rng)
    (root / "calib.txt").write_text("P0: 500 0 16 0 0 500 12 0 0 0 1 0\nP1: 500 0 16 -250 0 500 12 0 0 0 1 0\n")
    (root / "times.txt").write_text("0.0\n0.25\n0.5\n")
    clock = SimClock()
    cam = ReplayCamera({"path": str(root)}, clock)
    cam.connect()
    assert cam.dataset.stereo_baseline == pytest.approx(0.5)
    frames = [cam.read(timeout_s=1.0) for _ in range(4)]
    assert [f.meta["index"] for f in frames[:3]] == [0, 1, 2] and frames[3] is None and cam.finished
    assert all(f.right is not None and f.right.shape == (24, 32) for f in frames[:3])
    assert frames[2].stamp_ns - frames[0].stamp_ns == S // 2


def test_a_kitti_recording_whose_right_images_lag_the_left_is_refused(tmp_path, rng):
    """Left and right images were paired by their place in the sorted folders, counted but never named: a
    right folder that lost frame 2 and holds one more at the end (000000, 000001, 000003, 000004, 000005)
    gave every frame from 2 on the right image of a later exposure, and the obstacle stage matched a stereo
    pair taken at two moments (a false floor, a missed obstacle). A pair is one name in both folders."""
    root = tmp_path / "kitti"
    write_folder(root / "image_l", 5, rng)
    write_folder(root / "image_r", 6, rng)
    (root / "image_r" / "000002.png").unlink()
    (root / "calib.txt").write_text("P0: 500 0 16 0 0 500 12 0 0 0 1 0\nP1: 500 0 16 -250 0 500 12 0 0 0 1 0\n")
    with pytest.raises(CameraError, match=r"image_r/000002\.png: missing, .*image_l has it"):
        ReplayCamera({"path": str(root)}, SimClock()).connect()


def test_tum_replay_delivers_depth_in_metres(tmp_path, rng):
    root = tmp_path / "tum"
    write_folder(root / "rgb", 2, rng)
    (root / "depth").mkdir()
    for i in range(2):
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.full((24, 32), 5000 * (i + 1), np.uint16))
    (root / "rgb.txt").write_text("# colour\n10.0 rgb/000000.png\n10.1 rgb/000001.png\n")
    (root / "depth.txt").write_text("10.001 depth/0.png\n10.101 depth/1.png\n")
    (root / "camera.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32\nheight: 24\n")
    clock = SimClock()
    with ReplayCamera({"path": str(root)}, clock) as cam:
        f0, f1 = cam.read(), cam.read(timeout_s=1.0)
    assert f0.meta["depth"][0, 0] == pytest.approx(1.0) and f1.meta["depth"][0, 0] == pytest.approx(2.0)
    assert f1.stamp_ns - f0.stamp_ns == pytest.approx(S // 10, abs=1000)


def test_errors_name_the_missing_thing(tmp_path):
    with pytest.raises(CameraError, match="does not exist"):
        ReplayCamera({"path": str(tmp_path / "none")}, SimClock()).connect()
    (tmp_path / "empty").mkdir()
    with pytest.raises(CameraError, match="no images"):
        ReplayCamera({"path": str(tmp_path / "empty")}, SimClock()).connect()
    (tmp_path / "tum").mkdir()
    (tmp_path / "tum" / "rgb.txt").write_text("0 a.png\n")
    with pytest.raises(CameraError, match="a.png"):
        ReplayCamera({"path": str(tmp_path / "tum")}, SimClock()).connect()
    # KITTI's own folder name image_0/ without calib.txt: the missing calibration, not "no images" in the root
    (tmp_path / "kitti" / "image_0").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "kitti" / "image_0" / "000000.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(CameraError, match="calib.txt: missing"):
        ReplayCamera({"path": str(tmp_path / "kitti")}, SimClock()).connect()


def test_replays_the_real_kitti_sequence(shared_data):
    clock = SimClock()
    with ReplayCamera({"path": str(shared_data / "kitti06_stereo")}, clock) as cam:
        frames = []
        while (f := cam.read(timeout_s=1.0)) is not None:
            frames.append(f)
    assert len(frames) == 51 and frames[-1].right.shape == (370, 1226)
    assert (frames[-1].stamp_ns - frames[0].stamp_ns) == 5 * S  # 10 Hz without times.txt


def test_a_recording_whose_intrinsics_are_not_the_configured_camera_is_refused(tmp_path, rng):
    """A TUM or KITTI recording carries its camera (camera.yaml or camera_yaml, calib.txt): it was loaded and
    then ignored, and every stage ran on the configured intrinsics, which nothing compared with it. Another
    camera is now refused before a run, naming both; the same camera replays."""
    from vbnav.control.config import load_config
    from vbnav.drivers.errors import InputError
    root = tmp_path / "tum"
    write_folder(root / "rgb", 2, rng)
    (root / "rgb.txt").write_text("10.0 rgb/000000.png\n10.1 rgb/000001.png\n")
    (root / "cam.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32\nheight: 24\n")
    camera = {"driver": "replay", "width": 32, "height": 24, "fx": 25.0, "fy": 25.0, "cx": 16.0, "cy": 12.0,
              "options": {"path": str(root), "camera_yaml": str(root / "cam.yaml")}}
    cfg = load_config("sim", overrides={"camera": camera})
    with pytest.raises(InputError, match=r"cam\.yaml.*camera\.fx 25 vs the recording's 30.*camera\.fy 25") as e:
        ReplayCamera.from_config(cfg, SimClock())
    assert isinstance(e.value, CameraError)
    camera.update(fx=30.0, fy=30.0)
    cam = ReplayCamera.from_config(load_config("sim", overrides={"camera": camera}), SimClock())
    with cam:
        assert cam.read() is not None


@pytest.mark.parametrize("line, match", [
    ("width: 32.5", r"width: expected a whole number of pixels, got 32\.5"),
    ("width: '32'", r"width: expected a whole number of pixels, got '32'"),
    ("fx: true", r"fx: expected a number, got True"),
    ("cx: '16'", r"cx: expected a number, got '16'"),
])
def test_a_recordings_camera_yaml_takes_numbers_only(tmp_path, rng, line, match):
    """int() cut a width of 32.5 to 32 and float() read true as 1 px and '16' as 16: each a camera nobody
    wrote. They are errors naming the file and the key now, as in a calibration file."""
    root = tmp_path / "tum"
    write_folder(root / "rgb", 2, rng)
    (root / "rgb.txt").write_text("10.0 rgb/000000.png\n10.1 rgb/000001.png\n")
    values = dict(x.split(": ") for x in "fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32\nheight: 24".split("\n"))
    key, value = line.split(": ")
    values[key] = value
    (root / "camera.yaml").write_text("".join(f"{k}: {v}\n" for k, v in values.items()))
    with pytest.raises(CameraError, match=rf"camera\.yaml: {match}"):
        ReplayCamera({"path": str(root)}, SimClock()).connect()


@pytest.mark.parametrize("camera_extra, extra, says", [
    ({"distortion": [-0.2, 0.05, 0.0, 0.0, 0.0]}, {},
     r"camera\.distortion \[-0\.2, 0\.05, 0\.0, 0\.0, 0\.0\] vs the recording's \[\]"),
    ({"model": "fisheye"}, {}, r"camera\.model fisheye vs the recording's pinhole"),
    ({}, {"obstacles": {"baseline": 0.3}}, r"obstacles\.baseline 0\.3 m vs the recording's 0\.5 m"),
])
def test_a_recording_of_another_lens_or_rig_than_the_configured_one_is_refused(tmp_path, rng, camera_extra, extra,
                                                                               says):
    """check_camera compared fx, fy, cx, cy only: a KITTI recording (rectified: no distortion, its stereo
    baseline in calib.txt) replayed to stages configured with camera.distortion, a fisheye model or another
    obstacles.baseline ran them on a lens or a rig the images were not taken with, without a word. Each is
    refused now, naming the field and the recording's value; the recording's own lens and rig replay."""
    from vbnav.control.config import load_config
    from vbnav.drivers.camera import RecordedCameraError
    root = tmp_path / "kitti"
    write_folder(root / "image_l", 2, rng)
    write_folder(root / "image_r", 2, rng)
    (root / "calib.txt").write_text("P0: 500 0 16 0 0 500 12 0 0 0 1 0\nP1: 500 0 16 -250 0 500 12 0 0 0 1 0\n")
    camera = {"driver": "replay", "width": 32, "height": 24, "fx": 500.0, "fy": 500.0, "cx": 16.0, "cy": 12.0,
              "options": {"path": str(root)}}
    for same in ({"camera": camera}, {"camera": {**camera, "distortion": [0.0] * 5}, "obstacles": {"baseline": 0.5}}):
        ReplayCamera.from_config(load_config("sim", overrides=same), SimClock())
    bad = load_config("sim", overrides={"camera": {**camera, **camera_extra}, **extra})
    with pytest.raises(RecordedCameraError, match=r"calib\.txt.*" + says):
        ReplayCamera.from_config(bad, SimClock())


def test_a_camera_yaml_for_a_folder_of_images_is_refused(tmp_path, rng):
    """camera.options.camera_yaml is the intrinsics file of a TUM or KITTI recording; beside a plain folder of
    images (which takes its intrinsics from camera.*) it was accepted and never read. Refused, naming it."""
    write_folder(tmp_path / "seq", 2, rng)
    (tmp_path / "cam.yaml").write_text("fx: 30\nfy: 30\ncx: 16\ncy: 12\nwidth: 32\nheight: 24\n")
    with pytest.raises(CameraError, match=r"camera_yaml .*cam.yaml.*folder of images.*camera\.fx"):
        ReplayCamera({"path": str(tmp_path / "seq"), "camera_yaml": str(tmp_path / "cam.yaml")}, SimClock()).connect()
    with ReplayCamera({"path": str(tmp_path / "seq")}, SimClock()) as cam:
        assert cam.read() is not None
