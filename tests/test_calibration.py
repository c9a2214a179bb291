"""Calibration files: OpenCV YAML/XML and ROS camera_info, with clear errors."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vbnav.drivers.calibration import CalibrationError, load_calibration
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera

K = np.array([[520.5, 0, 321.2], [0, 519.8, 243.9], [0, 0, 1.0]])
D = np.array([0.11, -0.25, 0.001, -0.002, 0.08])


def write_opencv(path, k_name="camera_matrix", d_name="distortion_coefficients", model=None, d=D):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write(k_name, K)
    fs.write(d_name, d.reshape(1, -1))
    if model:
        fs.write("distortion_model", model)
    fs.release()


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
@pytest.mark.parametrize("names", [("camera_matrix", "distortion_coefficients"), ("K", "D")])
def test_opencv_filestorage(tmp_path, suffix, names):
    p = tmp_path / f"calib{suffix}"
    write_opencv(p, *names)
    cam = load_calibration(p)
    assert isinstance(cam, PinholeCamera)
    assert (cam.width, cam.height) == (640, 480)
    np.testing.assert_allclose(cam.K, K)
    np.testing.assert_allclose(cam.dist, D)


def test_opencv_fisheye(tmp_path):
    p = tmp_path / "fish.yaml"
    write_opencv(p, model="fisheye", d=np.array([0.01, -0.02, 0.003, -0.001]))
    cam = load_calibration(p)
    assert isinstance(cam, FisheyeCamera) and cam.dist == (0.01, -0.02, 0.003, -0.001)


ROS = """image_width: 640
image_height: 480
camera_name: front
camera_matrix:
  rows: 3
  cols: 3
  data: [520.5, 0, 321.2, 0, 519.8, 243.9, 0, 0, 1]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: {d}
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
"""


def test_ros_plumb_bob(tmp_path):
    p = tmp_path / "front.yaml"
    p.write_text(ROS.format(model="plumb_bob", n=5, d=D.tolist()))
    cam = load_calibration(p)
    assert isinstance(cam, PinholeCamera)
    np.testing.assert_allclose(cam.K, K)
    np.testing.assert_allclose(cam.dist, D)


def test_ros_rational_polynomial(tmp_path):
    p = tmp_path / "front.yaml"
    d8 = D.tolist() + [0.01, 0.02, 0.03]
    p.write_text(ROS.format(model="rational_polynomial", n=8, d=d8))
    assert len(load_calibration(p).dist) == 8


def test_ros_equidistant_is_fisheye(tmp_path):
    p = tmp_path / "front.yaml"
    p.write_text(ROS.format(model="equidistant", n=4, d=[0.1, 0.01, 0.0, 0.0]))
    cam = load_calibration(p)
    assert isinstance(cam, FisheyeCamera)
    # the model round-trips a ray (sanity of the loaded numbers)
    px, _ = cam.project(np.array([[0.3, -0.2, 1.0]]))
    ray = cam.rays(px)[0]
    np.testing.assert_allclose(ray, np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0]), atol=1e-9)


@pytest.mark.parametrize("text, match", [
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("image_width: 640\n", ""), "image_width: missing"),
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("[520.5, 0, 321.2, 0, 519.8, 243.9, 0, 0, 1]",
                                                            "[520.5, 0, 321.2]"), "camera_matrix: rows x cols is 3x3 = 9 numbers, data has 3"),
    (ROS.format(model="weird_model", n=5, d=D.tolist()), "distortion_model: 'weird_model' is not supported"),
    (ROS.format(model="plumb_bob", n=3, d=[0.1, 0.2, 0.3]), "distortion_coefficients: pinhole expects 4, 5"),
    ("foo: [1, 2", "not valid YAML"),
    ("width: 640\nheight: 480\n", "camera_matrix: missing"),
    # numpy reads "520.5" and true as numbers, and int() cuts 640.7 to 640: each was a camera nobody wrote
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("[520.5, 0,", "['520.5', 0,"),
     "camera_matrix.data: expected numbers, got '520.5'"),
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("[520.5, 0,", "[true, 0,"),
     "camera_matrix.data: expected numbers, got True"),
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("image_width: 640\n", "image_width: 640.7\n"),
     "image_width/image_height: expected whole numbers"),
    ("image_width: 640\nimage_height: '480'\ncamera_matrix: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n",
     "image_width/image_height: expected whole numbers"),
    # a NaN distortion coefficient loaded (and bent every ray to NaN)
    (ROS.format(model="plumb_bob", n=5, d="[.nan, 0.0, 0.0, 0.0, 0.0]"),
     r"distortion_coefficients: expected finite numbers, got \[nan, 0.0, 0.0, 0.0, 0.0\]"),
    # a skew or a bottom row other than 0 0 1 was accepted and never used (the models have fx, fy, cx, cy)
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("[520.5, 0, 321.2,", "[520.5, 40, 321.2,"),
     r"camera_matrix: expected \[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
    (ROS.format(model="plumb_bob", n=5, d=D.tolist()).replace("243.9, 0, 0, 1]", "243.9, 0, 0, 0]"),
     r"camera_matrix: expected \[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
])
def test_errors_name_file_and_field(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=match) as e:
        load_calibration(p)
    assert "bad.yaml" in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(CalibrationError, match="does not exist"):
        load_calibration(tmp_path / "nope.yaml")


def test_opencv_file_without_matrix(tmp_path):
    p = tmp_path / "c.yaml"
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.release()
    with pytest.raises(CalibrationError, match="c.yaml: camera_matrix: missing"):
        load_calibration(p)


OPENCV_K = "camera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [520.5, 0, 321.2, 0, 519.8, 243.9, 0, 0, 1]\n"


@pytest.mark.parametrize("text, match", [
    # a matrix whose data does not fill rows x cols, a matrix given as text or as a plain mapping: OpenCV's
    # own assertion escaped as a cv2.error traceback
    ("image_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n"
     "  data: [520.5, 0]\n", "camera_matrix: expected a matrix"),
    ("image_width: 640\nimage_height: 480\ncamera_matrix: hello\n", "camera_matrix: expected a matrix"),
    ("image_width: 640\nimage_height: 480\ncamera_matrix:\n  a: 1\n", "camera_matrix: expected a matrix"),
    ("image_width: 640\nimage_height: 480\n" + OPENCV_K + "distortion_coefficients: !!opencv-matrix\n"
     "  rows: 1\n  cols: 5\n  dt: d\n  data: [0.1]\n", "distortion_coefficients: expected a matrix"),
    # a width that is text was read as 1.8e308 px (FileNode.real() of a string), 640.7 cut to 640
    ("image_width: abc\nimage_height: 480\n" + OPENCV_K, "image_width: expected a whole number of pixels"),
    ("image_width: 640.7\nimage_height: 480\n" + OPENCV_K, "image_width: expected a whole number of pixels"),
])
def test_opencv_file_errors_name_file_and_field(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text("%YAML:1.0\n---\n" + text)
    with pytest.raises(CalibrationError, match=match) as e:
        load_calibration(p)
    assert "bad.yaml" in str(e.value)


@pytest.mark.parametrize("dist, expected", [("[.nan, 0, 0, 0]", "expected finite numbers"),
                                            ("[0.1, 0.2, 0.3]", "pinhole expects 4, 5, 8, 12 or 14")])
def test_a_dataset_camera_yaml_with_distortion_opencv_refuses_is_refused(tmp_path, dist, expected):
    """drivers/datasets.load_camera_yaml took any dist (NaN, 3 numbers): it is checked as every other camera
    reader checks it (vision/camera_model.check_distortion)."""
    from vbnav.drivers.datasets import DatasetError, load_camera_yaml
    p = tmp_path / "camera.yaml"
    p.write_text(f"fx: 400\nfy: 400\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\ndist: {dist}\n")
    with pytest.raises(DatasetError, match=f"{p}: dist: {expected}"):
        load_camera_yaml(p)


@pytest.mark.parametrize("n, d, field", [(5, [0.1, 0.01, 0.0, 0.0], "distortion_coefficients"),
                                         (8, D.tolist(), "distortion_coefficients")])
def test_ros_rows_and_cols_must_agree_with_the_data(tmp_path, n, d, field):
    """A camera_info whose data holds fewer numbers than its rows x cols (a coefficient lost in an edit or a
    cut copy) loaded with what was left: refused naming the field and both counts."""
    p = tmp_path / "front.yaml"
    p.write_text(ROS.format(model="plumb_bob", n=n, d=d))
    with pytest.raises(CalibrationError, match=rf"{p}: {field}: rows x cols is 1x{n} = {n} numbers, data has "
                                               rf"{len(d)}"):
        load_calibration(p)


def test_a_calibration_with_a_key_given_twice_is_refused(tmp_path):
    p = tmp_path / "front.yaml"
    p.write_text(ROS.format(model="plumb_bob", n=5, d=D.tolist()) + "image_width: 320\n")
    with pytest.raises(CalibrationError, match=rf"{p}: line \d+, column 1: .*duplicate key 'image_width'"):
        load_calibration(p)


@pytest.mark.parametrize("baseline", ["true", "'0.12'", ".nan", "-0.12"])
def test_a_dataset_camera_yaml_baseline_is_checked_as_a_frames(tmp_path, baseline):
    """The stereo baseline had two checks: check_baseline (calibration files, dataset camera YAML) and the
    stages' frame_baseline. The dataset YAML's went through float(): 'baseline: true' was a 1 m baseline (and
    a quoted '0.12' a number), where a frame's meta['baseline_m'] of either is refused. One check now,
    check_baseline, refuses what is not a distance > 0 in both."""
    import yaml
    from vbnav.drivers.calibration import CalibrationError, check_baseline
    from vbnav.drivers.datasets import DatasetError, load_camera_yaml
    p = tmp_path / "camera.yaml"
    p.write_text(f"fx: 400\nfy: 400\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\nbaseline: {baseline}\n")
    with pytest.raises(DatasetError, match=f"{p}: baseline: expected a finite stereo baseline > 0 m"):
        load_camera_yaml(p)
    with pytest.raises(CalibrationError, match="meta\\['baseline_m'\\]: expected a finite stereo baseline"):
        check_baseline("the frame", yaml.safe_load(f"b: {baseline}")["b"], "meta['baseline_m']")
    p.write_text("fx: 400\nfy: 400\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\nbaseline: 0.12\n")
    assert load_camera_yaml(p)[1]["baseline"] == 0.12


def test_a_dataset_camera_yaml_key_it_does_not_know_is_refused(tmp_path):
    """drivers/datasets.load_camera_yaml passed every key it did not read on as an extra: a misspelt
    'depth_scal: 0.0002' (vbnav vo --camera, the replay camera's camera_yaml) was accepted and the depth read at
    the default scale, five times too far. Unknown keys are refused as in every other configuration file,
    naming the key and the keys it takes."""
    from vbnav.drivers.datasets import DatasetError, load_camera_yaml
    p = tmp_path / "camera.yaml"
    p.write_text("fx: 400\nfy: 400\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\ndepth_scal: 0.0002\n")
    with pytest.raises(DatasetError, match=rf"{p}: depth_scal: unknown key.*depth_scale"):
        load_camera_yaml(p)
    p.write_text("fx: 400\nfy: 400\ncx: 320\ncy: 240\nwidth: 640\nheight: 480\ndepth_scale: 0.0002\n")
    assert load_camera_yaml(p)[1] == {"depth_scale": 0.0002}
