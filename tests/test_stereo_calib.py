"""Stereo calibration files: KITTI calib.txt and the vbnav stereo YAML, with clear errors."""
from __future__ import annotations

import pytest

from vbnav.drivers.stereo_calib import CalibrationError, load_stereo_calibration, read_kitti_calib

P0 = "7.07e+02 0 6.0e+02 0 0 7.07e+02 1.83e+02 0 0 0 1 0"
P1 = "7.07e+02 0 6.0e+02 -3.798e+02 0 7.07e+02 1.83e+02 0 0 0 1 0"


def test_kitti_labelled_and_bare(tmp_path):
    a = tmp_path / "calib.txt"
    a.write_text(f"P0: {P0}\nP1: {P1}\nP2: {P0}\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    b = tmp_path / "bare.txt"
    b.write_text(f"{P0}\n{P1}\n")
    for f in (a, b):
        c = load_stereo_calibration(f)
        assert (c.fx, c.fy, c.cx, c.cy) == (707.0, 707.0, 600.0, 183.0)
        assert c.baseline == pytest.approx(379.8 / 707.0)
        rig = c.rig(1226, 370)
        assert rig.fb == pytest.approx(379.8)


@pytest.mark.parametrize("text,match", [
    (f"P0: {P0}\n", "P1: missing"),
    (f"P0: {P0}\nP1: 1 2 3\n", "P1 .line 2.: expected 12 numbers"),
    (f"P0: {P0}\nP1: {P0}\n", "baseline"),
    (f"P0: {P0}\nP1: {P1.replace('1.83e+02', '1.9e+02')}\n", "not rectified"),
    ("P0: a b c\n", "line 1: expected numbers"),
])
def test_kitti_errors_name_file_and_field(tmp_path, text, match):
    f = tmp_path / "calib.txt"
    f.write_text(text)
    with pytest.raises(CalibrationError, match=match) as exc:
        load_stereo_calibration(f)
    assert str(f) in str(exc.value)


def test_yaml(tmp_path):
    f = tmp_path / "stereo.yaml"
    f.write_text("width: 640\nheight: 480\nfx: 400\nfy: 401\ncx: 319.5\ncy: 239.5\nbaseline: 0.075\n"
                 "mount: {height: 0.25, pitch_deg: 5}\ndisparity_scale: 0.125\n")
    c = load_stereo_calibration(f)
    assert c.rig().width == 640 and c.fy == 401 and c.baseline == 0.075
    assert c.mount_height == 0.25 and c.mount_pitch_deg == 5 and c.disparity_scale == 0.125
    with pytest.raises(CalibrationError, match="640x480"):
        c.rig(320, 240)


@pytest.mark.parametrize("text,match", [
    ("width: 640\nheight: 480\nfx: 400\nfy: 400\ncx: 1\ncy: 1\n", "baseline: Field required"),
    ("width: 640\nheight: 480\nfx: -4\nfy: 400\ncx: 1\ncy: 1\nbaseline: 0.1\n", "fx: Input should be greater than 0"),
    ("width: 640\nheight: 480\nfx: 4\nfy: 400\ncx: 1\ncy: 1\nbaseline: 0.1\nbasline: 2\n", "basline: unknown key"),
    ("width: 640\nheight: 480\nfx: 4\nfy: 400\ncx: 1\ncy: 1\nbaseline: 0.1\nmount: {pitch_deg: 3}\n",
     "mount.height: Field required"),
    ("- 1\n- 2\n", "expected a mapping"),
    ("a: [\n", "not valid YAML"),
    # lax pydantic read these as fx 1.0 and a 0.075 m baseline
    ("width: 640\nheight: 480\nfx: true\nfy: 400\ncx: 1\ncy: 1\nbaseline: 0.1\n", "fx: expected a number, not true"),
    ("width: 640\nheight: 480\nfx: 400\nfy: 400\ncx: 1\ncy: 1\nbaseline: '0.075'\n", "baseline: expected a number"),
])
def test_yaml_errors_name_file_and_field(tmp_path, text, match):
    f = tmp_path / "stereo.yml"
    f.write_text(text)
    with pytest.raises(CalibrationError, match=match) as exc:
        load_stereo_calibration(f)
    assert str(f) in str(exc.value)


def test_json_is_read_as_the_stereo_yaml(tmp_path):
    """A .json calibration was read as a KITTI calib.txt and refused as 'expected numbers' on line 1."""
    f = tmp_path / "stereo.json"
    f.write_text('{"width": 640, "height": 480, "fx": 400, "fy": 401, "cx": 319.5, "cy": 239.5, "baseline": 0.075}')
    c = load_stereo_calibration(f)
    assert c.fy == 401 and c.baseline == 0.075 and c.size == (640, 480)
    f.write_text('{"width": 640, "height": 480, "fx": true, "fy": 401, "cx": 319.5, "cy": 239.5, "baseline": 0.075}')
    with pytest.raises(CalibrationError, match="stereo.json: fx: expected a number"):
        load_stereo_calibration(f)


def test_missing_file(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        load_stereo_calibration(tmp_path / "nope.yaml")


def test_kitti_baseline_is_relative_to_p0(tmp_path):
    # both projection matrices shifted by the same translation: the baseline is their difference
    f = tmp_path / "calib.txt"
    shifted = P0.split()
    shifted[3] = "100.0"
    right = P1.split()
    right[3] = str(100.0 - 379.8)
    f.write_text(f"P0: {' '.join(shifted)}\nP1: {' '.join(right)}\n")
    assert read_kitti_calib(f).baseline == pytest.approx(379.8 / 707.0)


def test_kitti_left_camera_only(tmp_path):
    f = tmp_path / "calib.txt"
    f.write_text(f"# left camera only\nP0: {P0}\n")
    c = read_kitti_calib(f, need_right=False)
    assert c.baseline is None and c.camera(1226, 370).fx == 707.0
    with pytest.raises(CalibrationError, match="P1: missing"):
        read_kitti_calib(f)
    with pytest.raises(CalibrationError, match="no right camera"):
        c.rig(1226, 370)


@pytest.mark.realdata
@pytest.mark.parametrize("folder,fx,cx,cy,tx", [
    ("kitti06_stereo", 707.0912, 601.8873, 183.1104, 379.8145),      # bare lines
    ("vo_turns_kitti03", 721.5377, 609.5593, 172.854, 387.5744),     # labelled P0..P3
])
def test_kitti_reader_on_the_real_files(shared_data, folder, fx, cx, cy, tx):
    c = read_kitti_calib(shared_data / folder / "calib.txt")
    assert (c.fx, c.fy, c.cx, c.cy) == (fx, fx, cx, cy)
    assert c.baseline == tx / fx  # 0.5372 m for sequence 06 (data README), 0.5372 m for 03
    cam = c.camera(1226, 370)
    assert (cam.width, cam.height, cam.fx, cam.cy) == (1226, 370, fx, cy)
    assert c.rig(1226, 370).fb == pytest.approx(tx)


@pytest.mark.parametrize("name, text", [
    # KITTI's P1 with its tx in millimetre pixels: a 537 m baseline, every depth 1000 x too far
    ("calib.txt", "P0: 707 0 601 0 0 707 183 0 0 0 1 0\nP1: 707 0 601 -379814.5 0 707 183 0 0 0 1 0\n"),
    ("stereo.yaml", "width: 640\nheight: 480\nfx: 400\nfy: 400\ncx: 320\ncy: 240\nbaseline: 5.0e-12\n"),
])
def test_a_baseline_no_stereo_camera_has_is_refused(tmp_path, name, text):
    """5e9 m and 5e-12 m were taken (only > 0 was checked): every depth wrong by as many orders of magnitude."""
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(CalibrationError, match=rf"{p}: .*m is no stereo camera's baseline, expected between 0.001 "
                                               r"and 10 m \(a length in another unit than metres\?\)"):
        load_stereo_calibration(p)
