"""Settings written where nothing would read them are refused at load, naming the key and why; the same key
where it is read loads ("a setting that is accepted is used")."""
import pytest

from vbnav.control.config import ConfigError, load_config

STEREO_SIM = "camera: {driver: sim, options: {stereo_baseline: 0.075}}\n"
V4L2 = "camera: {driver: v4l2, options: {device: /dev/video0}}\n"


def load(tmp_path, text: str):
    p = tmp_path / "robot.yaml"
    p.write_text(text)
    return load_config(p)


def refused(tmp_path, text: str, *says: str) -> str:
    with pytest.raises(ConfigError) as exc:
        load(tmp_path, text)
    msg = str(exc.value)
    for s in says:
        assert s in msg, msg
    return msg


@pytest.mark.parametrize("key, value", [("sgbm_block_size", 5), ("sgbm_near_margin", 0.7)])
def test_sgbm_settings_beside_the_simulated_cameras_own_disparity_are_refused(tmp_path, key, value):
    """The simulated stereo camera sends its true disparity with every right image, and obstacles.source: auto
    takes a frame's own disparity when it has one (ObstacleStage._sgbm_pair): SGBM never ran, and an
    obstacles.sgbm_* setting was accepted and never used. Refused, naming it and saying source: sgbm matches the
    pair; with source sgbm it is used, and a switched-off obstacle stage keeps it."""
    obstacles = f"obstacles: {{enabled: true, {key}: {value}}}\n"
    msg = refused(tmp_path, STEREO_SIM + obstacles, f"obstacles.{key} sets the stereo matching (SGBM)",
                  "auto never runs with camera.driver sim", "sends its true disparity",
                  "set obstacles.source: sgbm")
    assert str(tmp_path / "robot.yaml") in msg
    used = load(tmp_path, STEREO_SIM + f"obstacles: {{enabled: true, source: sgbm, {key}: {value}}}\n")
    assert getattr(used.obstacles, key) == value
    assert getattr(load(tmp_path, STEREO_SIM + f"obstacles: {{{key}: {value}}}\n").obstacles, key) == value


def test_sgbm_settings_on_an_oak_are_refused(tmp_path):
    """An OAK sends its own disparity with every image: SGBM never runs on its frames (source auto takes it)."""
    pytest.importorskip("depthai")
    refused(tmp_path, "camera: {driver: oak}\nobstacles: {enabled: true, sgbm_near_margin: 0.7}\n",
            "obstacles.sgbm_near_margin sets the stereo matching (SGBM)", "camera.driver oak",
            "its own disparity with every image", "remove sgbm_near_margin")


@pytest.mark.parametrize("key, value", [("ground_band_ratio", 2.0), ("ground_corridor_half_width", 0.5),
                                        ("max_grade_change", 0.1), ("cross_slope_allowance", 0.1)])
def test_piecewise_ground_settings_with_one_plane_are_refused(tmp_path, key, value):
    """ground_model: plane fits one plane (ground_model_params returns None): the piecewise ground's settings
    were accepted and never read. Refused in the words of 'vbnav obstacles' refusing its options with
    --ground plane; with the piecewise ground they are used."""
    refused(tmp_path, f"obstacles: {{ground_model: plane, {key}: {value}}}\n",
            f"obstacles: {key}: shapes the piecewise ground", "ground_model: plane fits one plane",
            "set ground_model: piecewise")
    assert getattr(load(tmp_path, f"obstacles: {{ground_model: piecewise, {key}: {value}}}\n").obstacles,
                   key) == value


@pytest.mark.parametrize("key, value", [("max_candidates", 500), ("min_parallax_px", 20.0),
                                        ("refine_landmarks", False), ("weight_by_uncertainty", False),
                                        ("min_landmark_weight", 0.1)])
def test_monocular_landmark_settings_with_stereo_scale_are_refused(tmp_path, key, value):
    """A stereo VSLAM places every landmark from the pair (or the device's disparity): no candidate waits for
    parallax and no landmark is refined over its views or weighed by its uncertainty (vision/vslam.py
    _add_from_motion, _refine_landmarks, _confidence). These were accepted and never read; with metric_scale
    odometry they are used."""
    v = str(value).lower()
    refused(tmp_path, f"vslam: {{{key}: {v}}}\n", f"vslam: {key}: it sets a single camera's landmarks",
            "metric_scale stereo")
    assert getattr(load(tmp_path, f"vslam: {{metric_scale: odometry, {key}: {v}}}\n").vslam, key) == value


@pytest.mark.parametrize("key, value", [("max_tilt_deg", 4.0), ("tilt_smoothing", 0.2),
                                        ("tilt_threshold_pitch_deg", 0.5), ("tilt_threshold_roll_deg", 1.0)])
def test_tilt_settings_with_the_tilt_not_measured_are_refused(tmp_path, key, value):
    """vbc.tilt_sigma_deg 0 switches the repeat's tilt measurement off (RepeatStage._fix never solves it): its
    smoothing, thresholds and limit were accepted and never read. Refused; with the tilt measured they load."""
    refused(tmp_path, f"vbc: {{tilt_sigma_deg: 0, {key}: {value}}}\n", f"vbc: {key}: acts on the camera's tilt",
            "tilt_sigma_deg 0 switches that measurement off")
    assert getattr(load(tmp_path, f"vbc: {{tilt_sigma_deg: 1.0, {key}: {value}}}\n").vbc, key) == value
    assert load(tmp_path, "vbc: {tilt_sigma_deg: 0}\n").vbc.tilt_sigma_deg == 0


@pytest.mark.parametrize("key, text, value, says", [
    ("world", "corridor", "corridor", "sim.world 'corridor': the simulated world is built only for the simulated "
                                      "camera"),
    ("image_noise_std", "1.0", 1.0, "sim.image_noise_std 1: the simulated camera adds the image noise"),
    ("realtime", "true", True, "sim.realtime: true: the simulated clock runs only when the drive and the camera "
                               "are both"),
])
def test_simulated_camera_settings_with_another_camera_are_refused(tmp_path, key, text, value, says):
    """With the simulated drive and a real camera no world is built, no image simulated, and the robot runs on
    the wall clock anyway (make_robot, make_clock): sim.world, image_noise_std and realtime were accepted and
    never read. Refused, naming the camera; with the simulated camera they are used, and with a real drive the
    sim section is kept (the simulator is off)."""
    refused(tmp_path, V4L2 + f"sim: {{{key}: {text}}}\n", says, "camera.driver v4l2", f"remove sim.{key}")
    assert getattr(load(tmp_path, f"sim: {{{key}: {text}}}\n").sim, key) == value
    real = load(tmp_path, V4L2 + "drive: {driver: dynamixel, options: {port: /dev/ttyUSB0}}\n"
                                 f"sim: {{{key}: {text}}}\n")
    assert getattr(real.sim, key) == value


def test_the_simulated_drives_settings_load_beside_a_real_camera(tmp_path):
    """The simulated drive reads its own settings (the slip's seed and size, the motor, the start pose) with any
    camera: they load beside a real one."""
    cfg = load(tmp_path, V4L2 + "sim: {seed: 3, slip_std: 0.01, motor_time_constant_s: 0.1, "
                                "encoder_ticks_per_rev: 1024, wheel_accel_limit: 20.0, start_pose: [1.0, 0.0, 0.0]}\n")
    assert (cfg.sim.seed, cfg.sim.slip_std) == (3, 0.01)



def _steep(tmp_path, pitch_deg: float, extra: str = ""):
    p = tmp_path / "steep.yaml"
    p.write_text("camera:\n  mount: {height: 0.25, pitch_deg: %g}\n  options: {stereo_baseline: 0.12}\n"
                 "obstacles:\n  enabled: true\n  source: sgbm\n%s" % (pitch_deg, extra))
    return p


def test_an_sgbm_reach_beyond_256_disparities_is_refused(tmp_path):
    """A camera pitched 20 deg down, 0.25 m up, with a 12 cm baseline sees the floor from 0.203 m: 0.85 of that
    needs 288 disparities, and the stage cut them to 256 without a word (depths under 0.1875 m unmatched).
    Refused with the margin that accepts the reach; at that margin, or pitched up, it loads."""
    with pytest.raises(ConfigError, match=r"obstacles.sgbm_near_margin 0.85: .* nearest floor in view \(0.203 m.*"
                                          r"needs 288 disparities .* down to 0.188 m: set sgbm_near_margin to at "
                                          r"least 0.93"):
        load_config(_steep(tmp_path, 20.0))
    load_config(_steep(tmp_path, 20.0, "  sgbm_near_margin: 0.93\n"))
    load_config(_steep(tmp_path, 10.0))
    with pytest.raises(ConfigError, match="not even the nearest floor is reached"):
        load_config(_steep(tmp_path, 30.0))
