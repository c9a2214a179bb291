"""camera.calibration_file is loaded with the config and used everywhere (issue 14, point 1).

A missing or garbage file fails 'vbnav config check' naming the file; a ROS camera_info with fx 300 is the
camera the teach stage uses and the one the route manifest records (with the file and its hash); a repeat
refuses a route taught with another camera; a replay of images of another size is refused.
"""
from __future__ import annotations

import hashlib
import json

import cv2
import numpy as np
import pytest
import yaml

from vbnav.control import cli
from vbnav.control.config import CONFIG_DIR, ConfigError, load_config
from vbnav.control.route import RouteError, check_route_camera, load_route
from vbnav.control.session import Repeating, Teaching
from vbnav.drivers.calibration import calibration_problems, load_camera_calibration
from vbnav.drivers.camera import CameraSizeError
from vbnav.drivers.clock import SimClock
from vbnav.drivers.replay_camera import ReplayCamera

ROS_FX300 = """image_width: 640
image_height: 480
camera_name: front
camera_matrix: {rows: 3, cols: 3, data: [300.0, 0, 322.5, 0, 301.0, 241.0, 0, 0, 1]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [-0.1, 0.02, 0.0, 0.0, 0.0]}
"""


def config_with(tmp_path, calibration_file, **camera) -> str:
    data = yaml.safe_load((CONFIG_DIR / "sim.yaml").read_text())
    data["camera"]["calibration_file"] = calibration_file
    data["camera"].update(camera)
    p = tmp_path / "robot.yaml"
    p.write_text(yaml.safe_dump(data))
    return str(p)


def check(capsys, config: str) -> tuple[int, str]:
    code = cli.main(["config", "check", "-c", config])
    out = capsys.readouterr()
    return code, out.out + out.err


def test_missing_file_fails_config_check_naming_it(tmp_path, capsys):
    code, text = check(capsys, config_with(tmp_path, "nowhere.yaml"))
    assert code == 2
    assert "camera.calibration_file" in text and str(tmp_path / "nowhere.yaml") in text and "does not exist" in text


@pytest.mark.parametrize("garbage", ["camera_matrix: [1, 2\n", "just words\n", "image_width: 640\nimage_height: 480\n"
                                     "camera_matrix: {data: [0, 0, 0, 0, 0, 0, 0, 0, 1]}\n",
                                     "%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: [\n"])
def test_garbage_file_fails_config_check_naming_it(tmp_path, capsys, garbage):
    (tmp_path / "bad.yaml").write_text(garbage)
    code, text = check(capsys, config_with(tmp_path, "bad.yaml"))
    assert code == 2 and str(tmp_path / "bad.yaml") in text, text


def test_ros_camera_info_is_the_camera_of_the_teach_stage_and_the_manifest(tmp_path, capsys):
    (tmp_path / "front.yaml").write_text(ROS_FX300)
    config = config_with(tmp_path, "front.yaml")       # relative: from the config file's folder
    code, text = check(capsys, config)
    assert code == 0, text
    assert "from " + str(tmp_path / "front.yaml") in text and "fx 300.000 fy 301.000 cx 322.500" in text

    cfg = load_config(config)
    assert (cfg.camera.fx, cfg.camera.fy, cfg.camera.cx, cfg.camera.cy) == (300.0, 301.0, 322.5, 241.0)
    assert cfg.camera.distortion == [-0.1, 0.02, 0.0, 0.0, 0.0]
    teaching = Teaching(cfg, tmp_path / "route")
    assert teaching.stage.camera.fx == 300.0 and teaching.stage.camera.dist[0] == -0.1
    teaching.close(complete=False)
    manifest = json.loads((tmp_path / "route" / "manifest.json").read_text())
    assert manifest["camera"]["fx"] == 300.0
    rec = manifest["calibration"]
    assert rec["file"] == str(tmp_path / "front.yaml") and rec["format"] == "ros"
    assert rec["sha256"] == hashlib.sha256(ROS_FX300.encode()).hexdigest()
    assert (rec["fx"], rec["fy"], rec["cx"], rec["cy"], rec["width"], rec["height"]) == (300, 301, 322.5, 241, 640,
                                                                                          480)
    assert rec["distortion"][:2] == [-0.1, 0.02]


def test_a_calibration_for_another_size_is_an_error_naming_both(tmp_path):
    (tmp_path / "front.yaml").write_text(ROS_FX300)
    with pytest.raises(ConfigError, match=r"front.yaml is a calibration of 640x480 images, camera.width/height "
                                          r"say 320x240"):
        load_config(config_with(tmp_path, "front.yaml", width=320, height=240, cx=159.5, cy=119.5))


def test_stereo_yaml_gives_the_rig_and_a_conflicting_baseline_is_refused(tmp_path):
    (tmp_path / "rig.yaml").write_text("width: 640\nheight: 480\nfx: 410\nfy: 410\ncx: 320\ncy: 240\n"
                                       "baseline: 0.09\n")
    cfg = load_config(config_with(tmp_path, "rig.yaml"))
    assert cfg.camera.fx == 410 and cfg.camera.stereo_baseline() == 0.09
    from vbnav.control.stages.vslam import stereo_baseline_of
    assert stereo_baseline_of(cfg) == 0.09
    from vbnav.control.stages.line_map import LineMapStage   # the line map takes the file's rig too
    lines = LineMapStage.from_config(cfg)
    assert lines.baseline == 0.09 and lines.cam[0] == 410
    with pytest.raises(ConfigError, match="stereo baseline of 0.0900 m, camera.options.stereo_baseline says "
                                          "0.0600 m"):
        load_config(config_with(tmp_path, "rig.yaml", options={"stereo_baseline": 0.06}))


def test_a_stereo_yaml_mount_is_the_cameras_mount_and_a_different_camera_mount_is_refused(tmp_path):
    """A vbnav stereo YAML's ``mount:`` block was accepted and ignored as camera.calibration_file (only the offline
    'vbnav obstacles' read it): the stages used camera.mount's defaults. The file's mounting now replaces
    camera.mount's height, pitch and roll, as its intrinsics replace the inline ones; a camera.mount that says
    otherwise is refused naming both, as a conflicting baseline is."""
    (tmp_path / "rig.yaml").write_text("width: 640\nheight: 480\nfx: 410\nfy: 410\ncx: 320\ncy: 240\n"
                                       "baseline: 0.09\nmount: {height: 0.31, pitch_deg: 12.0, roll_deg: -1.5}\n")
    data = yaml.safe_load(open(config_with(tmp_path, "rig.yaml")).read())
    del data["camera"]["mount"]
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(data))
    cfg = load_config(tmp_path / "robot.yaml")
    m = cfg.camera.mount
    assert (m.height, m.pitch_deg, m.roll_deg) == (0.31, 12.0, -1.5), m
    from vbnav.control.stages.line_map import LineMapStage   # a stage takes the file's mounting
    assert LineMapStage.from_config(cfg).mount.height == 0.31
    same = config_with(tmp_path, "rig.yaml", mount={"height": 0.31, "forward": 0.2, "pitch_deg": 12.0,
                                                    "roll_deg": -1.5})
    assert load_config(same).camera.mount.forward == 0.2       # the rest of camera.mount stays the config's
    with pytest.raises(ConfigError, match=r"rig.yaml gives mount height 0.31 m, pitch_deg 12, roll_deg -1.5; "
                                          r"camera.mount says height 0.25 m, pitch_deg 0, roll_deg 0"):
        load_config(config_with(tmp_path, "rig.yaml"))       # sim.yaml's camera.mount


def test_a_stereo_yaml_disparity_scale_is_refused_as_the_camera_calibration(tmp_path):
    """``disparity_scale`` (px per unit of a stored integer disparity image) was accepted and ignored: only the
    offline 'vbnav obstacles --disparity' reads stored disparity images; a camera gives its disparity in px."""
    (tmp_path / "rig.yaml").write_text("width: 640\nheight: 480\nfx: 410\nfy: 410\ncx: 320\ncy: 240\n"
                                       "baseline: 0.09\ndisparity_scale: 0.0625\n")
    with pytest.raises(ConfigError, match="disparity_scale 0.0625.*vbnav obstacles"):
        load_config(config_with(tmp_path, "rig.yaml"))


def test_sanity_checks_for_doctor(tmp_path, capsys):
    (tmp_path / "front.yaml").write_text(ROS_FX300)
    assert calibration_problems(load_camera_calibration(tmp_path / "front.yaml")) == []
    (tmp_path / "mm.yaml").write_text(ROS_FX300.replace("300.0, 0", "3.6, 0").replace("301.0", "3.6"))
    problems = calibration_problems(load_camera_calibration(tmp_path / "mm.yaml"))
    assert len(problems) == 1 and "field of view" in problems[0]
    code, text = check(capsys, config_with(tmp_path, "mm.yaml"))       # legal, so valid, with the warning
    assert code == 0 and "warning: " + problems[0] in text


def test_repeat_refuses_a_route_taught_with_another_camera(tmp_path):
    (tmp_path / "front.yaml").write_text(ROS_FX300)
    taught_cfg = load_config(config_with(tmp_path, "front.yaml"))
    Teaching(taught_cfg, tmp_path / "route").close(complete=False)
    route = load_route(tmp_path / "route")
    check_route_camera(route, taught_cfg.camera.to_model())        # the same camera: accepted
    other = load_config("sim")          # fx 400 inline
    with pytest.raises(RouteError) as e:
        Repeating(other, route)
    msg = str(e.value)
    assert "fx 300.0" in msg and "front.yaml" in msg and "fx 400.0" in msg and "other intrinsics" in msg
    small = load_config("sim", overrides={"camera": {"width": 320, "height": 240, "cx": 159.5, "cy": 119.5,
                                                     "fx": 300, "fy": 301}})
    with pytest.raises(RouteError, match="another image size: pinhole 320x240"):
        Repeating(small, route)


def test_replay_of_images_of_another_size_is_refused(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), np.full((288, 384), 100, np.uint8))
    cfg = load_config("sim", overrides={"camera": {"driver": "replay", "options": {"path": str(tmp_path)}}})
    with pytest.raises(CameraSizeError, match=r"000.png is 384x288, the configuration expects 640x480"):
        ReplayCamera.from_config(cfg, SimClock())          # before any run starts
    with pytest.raises(CameraSizeError):
        ReplayCamera({"path": str(tmp_path)}, SimClock(), (640, 480)).connect()
    ok = load_config("sim", overrides={"camera": {"driver": "replay", "width": 384, "height": 288, "cx": 191.5,
                                                  "cy": 143.5, "options": {"path": str(tmp_path)}}})
    cam = ReplayCamera.from_config(ok, SimClock())
    cam.connect()
    assert cam.read(1.0).image.shape == (288, 384)


def test_teach_from_a_replay_of_another_size_is_refused_before_a_route_exists(tmp_path, capsys):
    img = tmp_path / "images"
    img.mkdir()
    for i in range(3):
        cv2.imwrite(str(img / f"{i:03d}.png"), np.full((288, 384), 100, np.uint8))
    data = yaml.safe_load((CONFIG_DIR / "sim.yaml").read_text())
    data["camera"].update(driver="replay", options={"path": str(img)})
    (tmp_path / "replay.yaml").write_text(yaml.safe_dump(data))
    code = cli.main(["teach", "-c", str(tmp_path / "replay.yaml"), "--out", str(tmp_path / "route"),
                     "--duration", "1"])
    assert code == 2 and "is 384x288, the configuration expects 640x480" in capsys.readouterr().err
    assert not (tmp_path / "route").exists()


def test_kitti_calib_txt_gives_the_rig_at_the_configured_size(tmp_path, shared_data, capsys):
    calib = shared_data / "kitti06_stereo" / "calib.txt"
    config = config_with(tmp_path, str(calib), width=1226, height=370, cx=600.0, cy=180.0)
    code, text = check(capsys, config)
    assert code == 0, text
    cfg = load_config(config)
    assert cfg.camera.calibration.format == "kitti" and abs(cfg.camera.stereo_baseline() - 0.537) < 0.002
    assert abs(cfg.camera.fx - 707.09) < 0.01 and "stereo baseline 0.53" in text


def test_the_simulated_camera_renders_the_stereo_rig_of_the_calibration_file(tmp_path):
    """A stereo calibration file's baseline replaces the inline values for every stage and the simulated
    camera (docs/hardware.md); the simulated camera took only camera.options.stereo_baseline, so with the
    rig in the file it rendered no right image and no disparity while the stereo stages waited for them."""
    from vbnav.control.runtime.factory import make_robot
    (tmp_path / "rig.yaml").write_text("width: 640\nheight: 480\nfx: 410\nfy: 410\ncx: 320\ncy: 240\n"
                                       "baseline: 0.09\n")
    cfg = load_config(config_with(tmp_path, "rig.yaml"))
    robot = make_robot(cfg, with_camera=True)
    assert robot.camera.stereo_baseline == 0.09
    robot.camera.connect()
    frame = robot.camera.read(timeout_s=1.0)
    assert frame is not None and frame.right is not None and frame.disparity is not None


def test_repeat_refuses_a_route_taught_with_another_lens_distortion(tmp_path):
    """Same model, size and intrinsics but another distortion is another lens: the current pixels would be
    turned into bearings that bend away from the taught ones towards the image border. It was accepted."""
    taught_cfg = load_config("sim")                    # distortion []
    Teaching(taught_cfg, tmp_path / "route").close(complete=False)
    route = load_route(tmp_path / "route")
    same = load_config("sim", overrides={"camera": {"distortion": [0.0, 0.0, 0.0, 0.0]}})
    check_route_camera(route, same.camera.to_model())  # no distortion written out: the same camera
    slight = load_config("sim", overrides={"camera": {"distortion": [-0.002, 0.001, 0.0, 0.0]}})
    check_route_camera(route, slight.camera.to_model())  # what a recalibration of the same lens moves
    other = load_config("sim", overrides={"camera": {"distortion": [-0.35, 0.12, 0.0, 0.0]}})
    with pytest.raises(RouteError) as e:
        Repeating(other, route)
    msg = str(e.value)
    assert "another lens distortion" in msg and "distortion [-0.35, 0.12, 0.0, 0.0]" in msg and \
        "distortion none" in msg


def test_repeat_refuses_a_camera_mount_moved_beyond_what_moves_a_fix_by_a_centimetre(tmp_path):
    """The route stores its camera mount; a repeat used the configured one without comparing: a camera
    mounted higher, further forward or to the side biases every fix. Refused beyond the change that moves a
    fix by MOUNT_FIX_BUDGET_M (the height's from the landmarks' elevations), naming both mounts."""
    import dataclasses
    import math
    from vbnav.control.route import MOUNT_FIX_BUDGET_M, check_route_mount, mount_tolerances
    cfg = load_config("sim")
    Teaching(cfg, tmp_path / "route").close(complete=False)
    route = load_route(tmp_path / "route")
    from test_route import make_kf      # landmarks all seen 0.25 rad below the horizon
    kfs = [dataclasses.replace(make_kf(np.random.default_rng(i), i), beta=np.full(20, 0.25)) for i in range(2)]
    route = dataclasses.replace(route, keyframes=kfs)
    tol = mount_tolerances(route)
    assert math.isclose(tol.height, MOUNT_FIX_BUDGET_M * math.tan(0.25)) and tol.offset == MOUNT_FIX_BUDGET_M == 0.01
    m = cfg.camera.mount
    check_route_mount(route, cfg.camera.mount.to_mount())            # the mount it was taught with
    for change in ({"height": m.height + 0.002}, {"forward": m.forward + 0.009}):   # within: accepted
        check_route_mount(route, load_config("sim", overrides={"camera": {"mount": change}}).camera.mount.to_mount())
    high = load_config("sim", overrides={"camera": {"mount": {"height": m.height + 0.004}}})
    with pytest.raises(RouteError) as e:
        Repeating(high, route)
    msg = str(e.value)
    assert f"height {m.height:.3f} m" in msg and f"height {m.height + 0.004:.3f} m" in msg, msg
    assert "height 4.0 mm off, beyond 2.6 mm" in msg and "camera.mount" in msg, msg
    side = load_config("sim", overrides={"camera": {"mount": {"lateral": m.lateral - 0.012}}})
    with pytest.raises(RouteError, match="lateral 12.0 mm off, beyond 10.0 mm"):
        Repeating(side, route)


def _route_seen_at(tmp_path, cfg, beta, range_m=4.0):
    """The route a teach with ``cfg`` starts, its landmarks all seen ``beta`` rad below the horizon at
    ``range_m`` m in the plane (a known height, the one of that range)."""
    import dataclasses
    import math
    from test_route import make_kf
    Teaching(cfg, tmp_path / "route").close(complete=False)
    route = load_route(tmp_path / "route")
    w = 1.0 / (range_m * math.tan(beta))
    kfs = [dataclasses.replace(make_kf(np.random.default_rng(i), i), beta=np.full(20, beta),
                               inv_height=np.full(20, w), inv_height_var=np.full(20, 1e-4 * w * w))
           for i in range(2)]
    return dataclasses.replace(route, keyframes=kfs)


def test_the_height_tolerance_of_a_near_horizon_route_is_never_below_what_a_tape_measure_reads(tmp_path):
    """Landmarks near the horizon made the height tolerance 1 cm x tan(beta): 0.2 mm at 0.02 rad, so a height
    measured again with a tape measure (1 mm) refused the route, though the taught height was measured to 1 mm
    too. It is never below MOUNT_MEASURE_M; steeper routes keep 1 cm x tan(beta)."""
    import math
    from vbnav.control.route import MOUNT_MEASURE_M, check_route_mount, mount_tolerances
    cfg = load_config("sim")
    m = cfg.camera.mount

    def mount(**change):
        return load_config("sim", overrides={"camera": {"mount": change}}).camera.mount.to_mount()
    flat = _route_seen_at(tmp_path / "flat", cfg, 0.02)
    assert MOUNT_MEASURE_M == 0.001 and mount_tolerances(flat).height == MOUNT_MEASURE_M
    check_route_mount(flat, mount(height=m.height + 0.0008))            # within a tape measure's reading
    with pytest.raises(RouteError, match="height 1.5 mm off, beyond 1.0 mm"):
        check_route_mount(flat, mount(height=m.height + 0.0015))
    steep = _route_seen_at(tmp_path / "steep", cfg, 0.5)                # 1 cm x tan(0.5) = 5.5 mm
    assert math.isclose(mount_tolerances(steep).height, 0.01 * math.tan(0.5))
    check_route_mount(steep, mount(height=m.height + 0.005))
    with pytest.raises(RouteError, match="height 6.0 mm off, beyond 5.5 mm"):
        check_route_mount(steep, mount(height=m.height + 0.006))


def test_repeat_refuses_a_camera_mount_turned_beyond_what_moves_the_image_points_as_a_centimetre(tmp_path):
    """check_route_mount compared height, forward and lateral only: a camera configured 5 deg further down, or
    turned in yaw (which no repeat measures), than the route was taught with was accepted. A turn by a moves
    every image point by fx a px, the 1 cm budget moves a landmark at range r by fx 0.01 / r px: beyond
    a = 0.01 / the landmarks' median range (4 m here: 0.14 deg) the repeat is refused, naming both mounts and
    the budget, by vbnav repeat and route check -c alike (config_repeat_refusal)."""
    import math
    from vbnav.control.route import MOUNT_MEASURE_RAD, check_route_mount, config_repeat_refusal, mount_tolerances
    cfg = load_config("sim")
    route = _route_seen_at(tmp_path, cfg, 0.25, range_m=4.0)
    tol = mount_tolerances(route)
    assert math.isclose(tol.range, 4.0) and math.isclose(tol.angle, 0.01 / 4.0)

    def config(**change):
        return load_config("sim", overrides={"camera": {"mount": change}})
    for within in ({"pitch_deg": 0.1}, {"yaw_deg": -0.12}, {"roll_deg": 0.13}):
        check_route_mount(route, config(**within).camera.mount.to_mount())
    down = config(pitch_deg=5.0)
    with pytest.raises(RouteError) as e:
        Repeating(down, route)
    msg = str(e.value)
    assert "pitch 0.00 deg" in msg and "pitch 5.00 deg" in msg, msg                     # both mounts
    assert "pitch 5.00 deg off, beyond 0.14 deg" in msg and "median range 4.0 m" in msg, msg
    assert f"{400 * 0.0025:.1f} px at fx 400" in msg, msg
    assert "pitch 5.00 deg off" in config_repeat_refusal(route, down)                   # route check -c
    for k in ("yaw_deg", "roll_deg"):
        assert f"{k[:-4]} 0.30 deg off, beyond 0.14 deg" in config_repeat_refusal(route, config(**{k: 0.3}))
    # far landmarks: never below what an inclinometer reads
    far = _route_seen_at(tmp_path / "far", cfg, 0.02, range_m=40.0)
    assert mount_tolerances(far).angle == MOUNT_MEASURE_RAD == math.radians(0.1)
    check_route_mount(far, config(pitch_deg=0.09).camera.mount.to_mount())
    assert "pitch 0.15 deg off, beyond 0.10 deg" in config_repeat_refusal(far, config(pitch_deg=0.15))
