"""``vbnav obstacles`` end to end: files in, JSON and PNGs out, clear errors."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import disparity_scenes as ds  # same directory

from vbnav.control.cli import main
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.stereo import StereoRig

RIG = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
SCENE = ds.Scene(0.25, 0.0, boxes=(ds.Box(-0.15, 0.15, 1.5, 1.7, 0.08),
                                   ds.Box(-30, 30, 12.0, 12.5, 8.0, texel=0.05)))
YAML = ("width: 640\nheight: 480\nfx: 400\nfy: 400\ncx: 319.5\ncy: 239.5\nbaseline: 0.075\n"
        "mount: {height: 0.25, pitch_deg: 0}\n")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    left, right, truth = ds.textured_pair(SCENE, RIG, rng=np.random.default_rng(2))
    cv2.imwrite(str(d / "l.png"), left)
    cv2.imwrite(str(d / "r.png"), right)
    cv2.imwrite(str(d / "l_copy.png"), left)
    np.save(d / "d.npy", np.nan_to_num(truth.disparity))
    (d / "stereo.yaml").write_text(YAML)
    return d, truth


def _run(capsys, *argv):
    code = main(["obstacles", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def test_pair_to_json_mask_and_overlay(files, capsys):
    d, truth = files
    code, out, err = _run(capsys, "--left", d / "l.png", "--right", d / "r.png", "--calib", d / "stereo.yaml",
                          "--obstacle-height", 0.02, "--mask-out", d / "m.png", "--overlay-out", d / "o.png")
    assert code == 0, err
    s = json.loads(out)
    assert s["disparity_source"] == "sgbm" and s["plane"]["fit_ok"]
    assert s["plane"]["camera_height_m"] == pytest.approx(0.25, abs=0.005)
    # the near band of the piecewise ground (0.42-0.59 m of floor): measured 0.095 deg on 2026-11-30
    # (one plane over the whole floor: 0.026 deg), bar 2x
    assert s["ground_model"] == "piecewise"
    assert abs(s["plane"]["pitch_deg"]) < 0.2
    assert s["nearest_obstacle"]["distance_m"] == pytest.approx(1.5, abs=0.05)
    assert abs(s["nearest_obstacle"]["bearing_deg"]) < 6
    assert sum(s["fractions"].values()) == pytest.approx(1.0, abs=1e-4)
    assert s["time_ms"]["total"] > 0
    mask = cv2.imread(str(d / "m.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (480, 640) and set(np.unique(mask)) <= {0, 1, 2, 255}
    box = truth.surface == ds.BOX0
    assert np.mean(mask[box] == 1) > 0.8            # the lowest 2 cm of its face are below the threshold
    floor = mask[truth.surface == ds.FLOOR]
    assert np.mean(floor == 1) < 0.01                   # SGBM (block 5) fattens the box onto the floor a little
    assert np.mean(floor[floor != 255] == 0) > 0.98     # SGBM leaves the leftmost columns unknown
    o = cv2.imread(str(d / "o.png"))
    assert o.shape == (480, 640, 3)
    assert not [p for p in d.iterdir() if p.name.startswith(".tmp-")]      # atomic writes leave nothing


def test_disparity_input(files, capsys):
    d, _ = files
    code, out, err = _run(capsys, "--disparity", d / "d.npy", "--calib", d / "stereo.yaml", "--noise-px", 0.0,
                          "--obstacle-height", 0.02, "--image", d / "l.png", "--overlay-out", d / "o2.png")
    assert code == 0, err
    s = json.loads(out)
    assert s["disparity_source"] == "file"
    assert s["nearest_obstacle"]["distance_m"] == pytest.approx(1.5, abs=0.02)
    assert (d / "o2.png").exists()


def test_16bit_disparity_png_uses_the_scale(files, capsys, tmp_path):
    d, truth = files
    png = tmp_path / "d16.png"
    cv2.imwrite(str(png), np.round(np.nan_to_num(truth.disparity) * 256).astype(np.uint16))   # KITTI devkit style
    code, out, err = _run(capsys, "--disparity", png, "--calib", d / "stereo.yaml", "--obstacle-height", 0.02)
    assert code == 0, err
    assert json.loads(out)["plane"]["camera_height_m"] == pytest.approx(0.25, abs=0.002)


@pytest.mark.parametrize("argv,match", [
    (["--left", "l.png", "--calib", "stereo.yaml"], "give --left and --right"),
    (["--left", "l.png", "--right", "r.png", "--disparity", "d.npy", "--calib", "stereo.yaml"], "either"),
    (["--left", "l.png", "--right", "r.png", "--calib", "missing.txt"], "missing.txt: calibration file not found"),
    (["--left", "nope.png", "--right", "r.png", "--calib", "stereo.yaml"], "nope.png: file not found"),
    (["--left", "stereo.yaml", "--right", "r.png", "--calib", "stereo.yaml"], "not an image"),
    # one image as both (given twice, or two copies) failed late, exit 1: "ground plane fit failed"
    (["--left", "l.png", "--right", "l.png", "--calib", "stereo.yaml"],
     "--left and --right are the same file, {d}/l.png: a stereo pair is two cameras' images"),
    (["--left", "l.png", "--right", "l_copy.png", "--calib", "stereo.yaml"],
     "left {d}/l.png and right {d}/l_copy.png are the same image: a stereo pair is two cameras' images"),
])
def test_bad_input_exit_2(files, capsys, argv, match):
    d, _ = files
    argv = [str(d / a) if a.endswith((".png", ".yaml", ".txt", ".npy")) else a for a in argv]
    code, out, err = _run(capsys, *argv)
    assert code == 2, err
    assert match.format(d=d) in err, err


NO_MOUNT = YAML.split("mount:")[0]                                  # no camera height known
KITTI = "P0: 400 0 319.5 0 0 400 239.5 0 0 0 1 0\nP1: 400 0 319.5 -30 0 400 239.5 0 0 0 1 0\n"   # 0.075 m


@pytest.mark.parametrize("argv,match", [
    # an option of the other input
    (["--left", "l.png", "--right", "r.png", "--image", "l.png"], "--image goes with --disparity"),
    (["--left", "l.png", "--right", "r.png", "--image", "/nonexistent.png"], "--image goes with --disparity"),
    (["--left", "l.png", "--right", "r.png", "--disparity-scale", "0.5"], "--disparity-scale scales a --disparity"),
    (["--disparity", "d.npy", "--block-size", "7"], "--block-size: set(s) OpenCV SGBM"),
    (["--disparity", "d.npy", "--min-depth", "0.5"], "--min-depth: set(s) OpenCV SGBM"),
    (["--disparity", "d.npy", "--image", "l.png"], "--image is the image --overlay-out draws on"),
    # the piecewise ground's settings with one plane
    (["--disparity", "d.npy", "--ground", "plane", "--ground-half-width", "2"], "--ground-half-width: shape(s)"),
    (["--disparity", "d.npy", "--ground", "plane", "--max-grade-change", "0.1"], "--ground plane fits one plane"),
    (["--disparity", "d.npy", "--ground", "plane", "--cross-slope-allowance", "0"], "--cross-slope-allowance"),
    (["--disparity", "d.npy", "--calib", "nomount.yaml", "--max-grade-change", "0.1"],
     "--ground auto without a camera height (--camera-height"),
    # the mounting without a camera height: the fit is unseeded
    (["--disparity", "d.npy", "--calib", "nomount.yaml", "--pitch-deg", "5"], "--pitch-deg: the mounting needs"),
    (["--disparity", "d.npy", "--calib", "nomount.yaml", "--roll-deg", "1"], "--roll-deg: the mounting needs"),
    (["--disparity", "d.npy", "--calib", "calib.txt", "--height-tol", "0.1", "--tilt-tol-deg", "3"],
     "--height-tol, --tilt-tol-deg: the mounting needs the camera height"),
])
def test_options_that_do_not_apply_are_refused(files, capsys, argv, match):
    """An option the chosen input or ground model would not use is refused, naming it and why (it was ignored,
    exit 0: with a KITTI calib.txt the output said "used_prior": false)."""
    d, _ = files
    (d / "nomount.yaml").write_text(NO_MOUNT)
    (d / "calib.txt").write_text(KITTI)
    if "--calib" not in argv:
        argv = [*argv, "--calib", "stereo.yaml"]
    argv = [str(d / a) if a.endswith((".png", ".yaml", ".txt", ".npy")) and "/" not in a else a for a in argv]
    code, out, err = _run(capsys, *argv)
    assert code == 2 and out == "", err
    assert len(err.strip().splitlines()) == 1 and match in err, err


def test_settings_that_apply_are_used(files, capsys):
    """The same options where they apply: accepted, and they change the result."""
    d, _ = files
    (d / "nomount.yaml").write_text(NO_MOUNT)
    base = ["--disparity", d / "d.npy", "--noise-px", 0.0, "--obstacle-height", 0.02]
    code, out, err = _run(capsys, *base, "--calib", d / "nomount.yaml", "--camera-height", 0.25,
                          "--pitch-deg", 0.0, "--height-tol", 0.01)
    assert code == 0, err
    s = json.loads(out)
    assert s["ground_model"] == "piecewise" and s["plane"]["fit_ok"]
    code, out, err = _run(capsys, *base, "--calib", d / "stereo.yaml", "--ground-half-width", 0.05)
    assert code == 0, err
    assert json.loads(out)["ground_bands"] != s["ground_bands"]


def test_image_size_must_match_calibration(files, capsys, tmp_path):
    d, _ = files
    small = tmp_path / "s.png"
    cv2.imwrite(str(small), np.zeros((240, 320), np.uint8))
    code, _, err = _run(capsys, "--left", small, "--right", small, "--calib", d / "stereo.yaml")
    assert code == 2 and "640x480" in err


@pytest.mark.realdata
def test_kitti_frame(shared_data, capsys, tmp_path):
    k = shared_data / "kitti06_stereo"
    code, out, err = _run(capsys, "--left", k / "image_l" / "000025.png", "--right", k / "image_r" / "000025.png",
                          "--calib", k / "calib.txt", "--camera-height", 1.65, "--obstacle-height", 0.1,
                          "--max-height", 2.0, "--corridor-half-width", 3.0, "--corridor-range", 20,
                          "--ground-half-width", 1.75, "--mask-out", tmp_path / "m.png")   # half a lane
    assert code == 0, err
    s = json.loads(out)
    assert s["plane"]["camera_height_m"] == pytest.approx(1.65, abs=0.07)
    n = s["nearest_obstacle"]           # the left curb (~5 m) or the parked car on the right (~7 m)
    assert n is not None and 4.0 < n["distance_m"] < 10.0
    mask = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (370, 1226)
    assert np.mean(mask[195:330, 820:1110] == 1) > 0.8          # the parked car
    assert np.mean(mask[300:365, 500:760] == 0) > 0.95           # the road ahead
