"""Bad configurations stop start-up with the file, key path and expectation."""
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from vbnav.control.cli import main
from vbnav.control.config import Config, ConfigError, load_config, parse_config

REPO = Path(__file__).resolve().parent.parent


def write(tmp_path, text: str) -> Path:
    p = tmp_path / "robot.yaml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, key, expected", [
    ("robot:\n  wheel_radius: -0.05\n", "robot.wheel_radius", "greater than 0"),
    ("loop:\n  rate_hz: 0\n", "loop.rate_hz", "greater than 0"),
    ("robot:\n  wheel_radius: fast\n", "robot.wheel_radius", "valid number"),
    # lax pydantic read these as 1.0 m/s, 15 Hz, 0.2 m and False: values nobody wrote
    ("robot:\n  max_linear_speed: true\n", "robot.max_linear_speed", "expected a number, not true/false"),
    # .inf passed the lower bounds and switched off what it set: no obstacle is ever taller, no fix gate
    ("obstacles:\n  obstacle_height: .inf\n", "obstacles.obstacle_height", "expected a finite number, not inf"),
    ("vbc:\n  fix_gate_m: .inf\n", "vbc.fix_gate_m", "expected a finite number, not inf"),
    ("vbc:\n  tilt_smoothing: .nan\n", "vbc.tilt_smoothing", "expected a finite number, not nan"),
    ("camera:\n  rate_hz: '15'\n", "camera.rate_hz", "not the text '15'"),
    ("vbc:\n  fix_gate_m: '0.2'\n", "vbc.fix_gate_m", "not the text '0.2'"),
    ("vslam:\n  min_parallax_px: yes\n", "vslam.min_parallax_px", "not true/false"),
    ("obstacles:\n  negative_stops: 'no'\n", "obstacles.negative_stops", "expected true or false"),
    ("drive:\n  driver: sim\n  options:\n    fail_after_s: true\n", "drive.options.fail_after_s", "not true/false"),
    ("robot:\n  wheel_radus: 0.05\n", "robot.wheel_radus", "unknown key"),
    ("source: elsewhere.yaml\n", "source", "unknown key"),        # not a setting: the file loaded
    ("drive:\n  driver: sim\n  invert_right: true\n", "drive.invert_left/invert_right", "'sim' has none"),
    ("sim:\n  world: nope\n", "sim.world", "'corridor_step'"),         # at load, not when the camera opens
    ("drive:\n  driver: warp\n", "drive.driver", "unknown driver 'warp'"),
    ("camera:\n  driver: kinect\n", "camera.driver", "expected one of"),
    ("loop:\n  overrun_policy: hope\n", "loop.overrun_policy", "'skip' or 'catch_up'"),
    ("camera:\n  mount:\n    pitch_deg: 120\n", "camera.mount.pitch_deg", "less than or equal to 90"),
    ("drive:\n  driver: sim\n  options:\n    fail_after_s: -1\n", "drive.options.fail_after_s", "greater than 0"),
    ("robot:\n  max_linear_speed: 5.0\n", "max_linear_speed", "exceeds what the wheels can do"),
    # a slow zone of the stop zone's name would share (and clear) its trigger history
    ("obstacles:\n  zones:\n    - {name: z, action: stop, distance: 0.8, half_width: 0.25}\n"
     "    - {name: z, action: slow, distance: 1.5, half_width: 0.35}\n", "obstacles", "'z' given more than once"),
])
def test_bad_values_name_file_key_and_expectation(tmp_path, text, key, expected):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert str(p) in msg and key in msg and expected in msg, msg


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")
    p = write(tmp_path, "robot: [1, 2\n")
    with pytest.raises(ConfigError, match=r"robot.yaml: line \d+, column \d+: not valid YAML"):
        load_config(p)
    p = write(tmp_path, "- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(p)


def test_cli_exits_nonzero_with_message(tmp_path, capsys):
    p = write(tmp_path, "robot:\n  wheel_radius: -1\n")
    assert main(["config", "check", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "robot.wheel_radius" in err and str(p) in err
    assert main(["run", "--config", str(p), "--duration", "1"]) == 2


def test_cli_subprocess_exit_code(tmp_path):
    p = write(tmp_path, "loop:\n  rate_hz: 0\n")
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "run", "--config", str(p)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "loop.rate_hz" in r.stderr


def test_every_shipped_config_loads():
    files = sorted((REPO / "configs").glob("*.yaml"))
    assert files
    for f in files:
        cfg = load_config(f)
        assert cfg.robot.wheel_radius > 0


def test_defaults_match_sim_yaml():
    """configs/sim.yaml spells out the defaults; drift between them would confuse users."""
    data = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    assert parse_config(data).model_dump() == Config.model_validate(data).model_dump()
    assert Config().model_dump()["robot"] == Config.model_validate(data).model_dump()["robot"]


def field_paths(model, prefix: str = ""):
    """(key path, field) of every field of a model, nested models included ('obstacles.zones[].name')."""
    from vbnav.control.commands.config import nested_model
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        key = f"{prefix}.{name}" if prefix else name
        yield key, field
        sub, how = nested_model(field.annotation)
        if sub is not None:
            yield from field_paths(sub, key + ("[]" if how == "list" else ""))


def test_reference_documents_every_key_of_every_section_and_driver():
    from vbnav.control.commands.config import reference_markdown
    from vbnav.drivers import registry
    ref = reference_markdown(Config)
    paths = dict(field_paths(Config))
    assert {"vbc.max_features", "vslam.goto.k_beta", "obstacles.zones[].polygon", "telemetry.auth.usrpwd.user",
            "camera.mount.pitch_deg"} <= set(paths)
    missing = [k for k in paths if f"`{k}`" not in ref]
    assert not missing, f"not in the reference: {missing}"
    undescribed = [k for k, f in paths.items() if not f.description]
    checked = 0
    for section, table in (("camera", registry.CAMERAS), ("drive", registry.DRIVES)):
        for name in table:
            title = f"### `{section}.driver: {name}`"
            assert title in ref, title
            part = ref.split(title, 1)[1].split("\n#", 1)[0]     # up to the next heading
            if registry.missing_sdk(table, name):
                assert "not installed here" in part
                continue
            for key, field in field_paths(registry.load(table, name).Options, f"{section}.options"):
                assert f"| `{key}` |" in part, (name, key)
                checked += 1
                if not field.description:
                    undescribed.append(f"{key} ({name})")
    assert checked >= 40, checked
    assert not undescribed, f"keys without a description: {undescribed}"


@pytest.mark.parametrize("text, key", [
    ("vbc:\n  cruise_sped: 0.2\n", "vbc.cruise_sped"),
    ("obstacles:\n  enabled: maybe\n", "obstacles.enabled"),
    ("telemetry:\n  rate_hz: -5\n", "telemetry.rate_hz"),
])
def test_feature_sections_are_validated_at_load(tmp_path, text, key):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(p) in str(err.value) and key in str(err.value), str(err.value)


def test_reference_names_a_driver_whose_sdk_is_missing_instead_of_importing_it(monkeypatch):
    from vbnav.control.commands.config import reference_markdown
    from vbnav.drivers import registry
    monkeypatch.setitem(registry.SDKS, "vbnav.drivers.oak_camera", "no_such_sdk_here")
    load = registry.load

    def load_all_but_oak(table, name):
        assert name != "oak", "the OAK driver was imported although its SDK is missing"
        return load(table, name)
    monkeypatch.setattr(registry, "load", load_all_but_oak)
    part = reference_markdown(Config).split("### `camera.driver: oak`", 1)[1].split("\n#", 1)[0]
    assert "needs the `no_such_sdk_here` package, which is not installed here" in part


@pytest.mark.parametrize("script, expected", [
    ("[[.nan, 0.0, 3.0]]", "finite"),
    ("[[0.3, .inf, 3.0]]", "finite"),
    ("[[0.3]]", "[linear, angular, seconds]"),
    ("[[0.3, 0.0, -1.0]]", "seconds > 0"),
    ("[]", "no segments"),
])
def test_a_scripted_drive_that_cannot_be_driven_is_refused_at_load(tmp_path, script, expected):
    """controller.script took any lists of numbers: a NaN segment loaded, started the run and ended it with an
    exception in its first cycle; a short or negative segment loaded and failed when `vbnav run` built the
    controller (`vbnav config check` said it was fine)."""
    p = write(tmp_path, f"controller:\n  script: {script}\n")
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert "controller.script" in msg and expected in msg, msg


@pytest.mark.parametrize("camera,says", [
    ({"distortion": [-0.3, 0.1, 0.0, 0.0, 0.0]}, "camera.distortion [-0.3, 0.1, 0.0, 0.0, 0.0]"),
    ({"model": "fisheye", "distortion": [0.0, 0.0, 0.0, 0.0]}, "camera.model fisheye"),
])
def test_obstacles_on_a_distorted_camera_are_refused(camera, says):
    """The obstacle stage builds a plain pinhole camera from fx, fy, cx, cy ('rectified: no distortion'): with
    camera.distortion or a fisheye model it read the distorted images as rectified, every floor distance and
    the zones' outline wrong, without a word. Such a config is refused, naming the field; zeros are no
    distortion (the sentry configs write them)."""
    cfg = {"camera": {"options": {"stereo_baseline": 0.075}, **camera}, "obstacles": {"enabled": True}}
    with pytest.raises(ConfigError, match=re.escape(says)) as err:
        parse_config(cfg, "robot.yaml")
    assert "robot.yaml: obstacles.enabled" in str(err.value) and "rectified" in str(err.value)
    parse_config({**cfg, "obstacles": {"enabled": False}})           # the other stages use the distortion
    parse_config({"camera": {"options": {"stereo_baseline": 0.075}, "distortion": [0.0] * 5},
                  "obstacles": {"enabled": True}})


@pytest.mark.parametrize("text, expected", [
    ("  distortion: [.nan, 0, 0, 0]\n", "expected finite numbers"),
    ("  distortion: [0.1, 0, .inf, 0, 0]\n", "expected finite numbers"),
    ("  distortion: [0.1, 0, 0]\n", "pinhole expects 4, 5, 8, 12 or 14 coefficients (or none), got 3"),
    ("  distortion: [0.1, 0, 0, 0, 0, 0]\n", "pinhole expects 4, 5, 8, 12 or 14 coefficients (or none), got 6"),
    # a fisheye with 2 was padded with zeros, one with 6 cut to 4: coefficients nobody calibrated
    ("  model: fisheye\n  distortion: [0.1, 0.1]\n", "fisheye expects 4 coefficients (or none), got 2"),
])
def test_distortion_opencv_would_refuse_is_refused_at_load(tmp_path, text, expected):
    """NaN, inf or a coefficient count OpenCV refuses loaded, and failed (or bent every bearing) in the first
    undistortPoints of the run; refused at load, naming the file and the field."""
    p = write(tmp_path, "camera:\n" + text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert str(p) in msg and "camera.distortion" in msg and expected in msg, msg


@pytest.mark.parametrize("text, key, line", [
    ("camera:\n  fx: 410\n  fy: 410\n  fx: 500\n", "fx", 4),
    # a second section replaced the first whole: the drive's settings above were silently dropped
    ("robot:\n  wheel_radius: 0.04\nloop:\n  rate_hz: 50\nrobot:\n  max_linear_speed: 0.3\n", "robot", 5),
])
def test_a_key_given_twice_is_refused_naming_both_lines(tmp_path, text, key, line):
    """YAML readers keep the last of two equal keys: the first value was silently not used."""
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert str(p) in msg and f"line {line}" in msg and f"duplicate key '{key}'" in msg, msg


def test_an_unknown_drive_driver_is_named_as_unknown_not_as_a_real_drive():
    """configs/sim.yaml with `drive.driver: bogus` said "controller.teach 'room_loop' drives the simulated
    room's loop; drive.driver 'bogus' is a real drive (use teach: teleop)": the misspelt driver was taken for
    a real one, and the advice was to change an unrelated key. It is now 'unknown driver', as with teach:
    teleop."""
    data = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "sim.yaml").read_text())
    assert data["controller"]["teach"] == "room_loop"
    data["drive"]["driver"] = "bogus"
    with pytest.raises(ConfigError, match=r"drive\.driver: unknown driver 'bogus'; expected one of .*sim"):
        parse_config(data, "robot.yaml")


def test_a_bundle_adjustment_window_with_stereo_scale_is_refused():
    """`vslam: {ba_window: 7}` on a stereo robot (metric_scale stereo, the default) was accepted and never
    ran: the window adjusts landmarks placed by the camera's own motion, and the pair measures every
    landmark of a stereo VSLAM. It is refused naming both keys; with metric_scale odometry it is taken."""
    with pytest.raises(ConfigError, match=r"robot\.yaml: vslam: .*ba_window 7.*metric_scale stereo"):
        parse_config({"vslam": {"ba_window": 7}}, "robot.yaml")
    assert parse_config({"vslam": {"ba_window": 7, "metric_scale": "odometry"}}, "robot.yaml").vslam.ba_window == 7


def test_an_obstacle_baseline_that_disagrees_with_the_cameras_is_refused():
    """obstacles.baseline was compared with a calibration file's baseline only: beside the simulated camera's
    camera.options.stereo_baseline it was taken as given, so one rig had two baselines in one run (the obstacle
    stage used obstacles.baseline; the VSLAM of goto and the line map of map build, the camera's) and every
    obstacle depth was off by their ratio. Refused beyond 1 % (BASELINE_AGREEMENT), naming both."""
    from vbnav.control.config import ConfigError, load_config
    with pytest.raises(ConfigError, match=r"obstacles\.baseline 0\.1 m.*camera\.options\.stereo_baseline "
                                          r"0\.075 m"):
        load_config("sim_stereo", overrides={"obstacles": {"baseline": 0.1}})
    assert load_config("sim_stereo", overrides={"obstacles": {"baseline": 0.0752}}).obstacles.baseline == 0.0752
    assert load_config("sim", overrides={"obstacles": {"baseline": 0.1}}).obstacles.baseline == 0.1


def test_a_slow_scale_on_a_stop_zone_is_refused():
    """obstacles.zones[].slow_scale is the speed factor of a slow zone: given on a stop zone (an edit that
    meant 'slow down here' and forgot action: slow) it was accepted and the zone stopped the robot. Refused,
    naming the zone and the field; a slow zone takes it."""
    zone = {"name": "front", "distance": 0.8, "half_width": 0.25, "slow_scale": 0.5}
    with pytest.raises(ConfigError, match=r"obstacles\.zones.*zone 'front': slow_scale 0\.5 .*action: stop"):
        load_config("sim", overrides={"obstacles": {"zones": [zone]}})
    cfg = load_config("sim", overrides={"obstacles": {"zones": [{**zone, "action": "slow"}]}})
    assert cfg.obstacles.zones[0].slow_scale == 0.5


@pytest.mark.parametrize("key, value", [("sgbm_block_size", 5), ("sgbm_near_margin", 0.7)])
def test_sgbm_settings_with_the_frames_own_disparity_are_refused(key, value):
    """obstacles.source: disparity takes the frames' own disparity (an OAK's) and never runs SGBM: an
    obstacles.sgbm_* setting beside it was accepted and never used. Refused, naming both; with source sgbm or
    auto (SGBM on frames without a disparity) it is taken."""
    with pytest.raises(ConfigError, match=rf"obstacles.*{key} .*source: disparity"):
        load_config("sim", overrides={"obstacles": {"source": "disparity", key: value}})
    for source in ("sgbm", "auto"):
        assert getattr(load_config("sim", overrides={"obstacles": {"source": source, key: value}}).obstacles,
                       key) == value


@pytest.mark.parametrize("name", sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "configs").glob("*.yaml")))
def test_config_show_prints_a_configuration_that_loads_back_as_the_same(name, tmp_path, capfd):
    """'vbnav config show' prints every field, defaults included. The refusals of settings written where they
    do not apply (a stop zone's slow_scale, vslam settings of the other metric_scale, sgbm settings beside the
    frames' own disparity) took a default printed by show as written, so no shown configuration loaded back;
    and the OAK configuration's shown YAML began with depthai's import warning, printed on stdout."""
    assert main(["config", "show", "-c", name]) == 0
    shown = tmp_path / f"{name}.yaml"
    shown.write_text(capfd.readouterr().out)
    assert load_config(shown).model_dump() == load_config(name).model_dump()


@pytest.mark.parametrize("camera,says", [
    ({"driver": "sim"}, "the simulated camera renders a right image only with a stereo baseline"),
    ({"driver": "v4l2", "options": {"device": "/dev/video0"}}, "camera.driver v4l2 gives one image per frame"),
])
def test_sgbm_obstacles_on_a_camera_without_a_right_image_are_refused_at_load(camera, says):
    """obstacles.source: sgbm matches the frame's stereo pair; on a camera that gives no right image the config
    loaded (`vbnav config check` said it was fine) and every frame of the run was blind: the robot held for good.
    Refused at load, naming the field and the camera; a stereo simulated camera loads."""
    cfg = {"camera": camera, "obstacles": {"enabled": True, "source": "sgbm", "baseline": 0.075}}
    with pytest.raises(ConfigError, match=re.escape(says)) as err:
        parse_config(cfg, "robot.yaml")
    assert "robot.yaml: obstacles.source: sgbm" in str(err.value), err.value
    parse_config({**cfg, "obstacles": {"enabled": False, "source": "sgbm"}})       # no stage, nothing to match
    parse_config({"camera": {"driver": "sim", "options": {"stereo_baseline": 0.075}},
                  "obstacles": {"enabled": True, "source": "sgbm"}})


@pytest.mark.parametrize("camera, instead", [
    ({"driver": "replay", "rate_hz": 30.0, "options": {"path": "rec"}}, "camera.options.rate_hz"),
    ({"driver": "oak", "rate_hz": 30.0, "options": {"replay_file": "rec.mp4"}}, "camera.options.replay_fps"),
])
def test_a_camera_rate_the_recording_camera_never_reads_is_refused(camera, instead):
    """camera.rate_hz written for the replay camera (it plays at the recorded times, its options.rate_hz or 10 Hz)
    or the OAK's host-only replay_file (its options.replay_fps) was accepted and never read: a folder of images
    played at 10 Hz beside rate_hz: 30. Refused at load, naming the field and the one that sets the rate."""
    with pytest.raises(ConfigError, match=rf"camera\.rate_hz 30 .*{re.escape(instead)}"):
        parse_config({"camera": camera})
    camera = dict(camera, rate_hz=15.0)         # the default, as 'vbnav config show' writes it: loads
    assert parse_config({"camera": camera}).camera.rate_hz == 15.0


@pytest.mark.parametrize("camera,says", [
    ({"driver": "sim"}, "the simulated camera renders a right image only with a stereo baseline"),
    ({"driver": "v4l2", "options": {"device": "/dev/video0"}}, "camera.driver v4l2 gives one image per frame"),
    ({"driver": "oak", "options": {"disparity": False}}, "camera.options.disparity: false"),
    ({"driver": "oak", "options": {"replay_file": "rec.mp4"}}, "camera.options.replay_file replays images only"),
])
@pytest.mark.parametrize("source", ["auto", "disparity"])
def test_obstacles_on_a_camera_without_disparity_or_a_pair_are_refused_at_load(camera, says, source):
    """obstacles.enabled (source auto or disparity) on a camera whose frames carry neither a disparity nor a
    right image loaded, and every frame of the run was blind ('frame has no disparity'): the robot held for
    good. Refused at load, naming the field and the camera, as source: sgbm already was; stereo cameras load."""
    with pytest.raises(ConfigError, match=re.escape(says)) as err:
        parse_config({"camera": camera, "obstacles": {"enabled": True, "source": source}}, "robot.yaml")
    assert "robot.yaml: obstacles.enabled" in str(err.value), err.value
    parse_config({"camera": camera, "obstacles": {"enabled": False, "source": source}})   # no stage: kept
    parse_config({"camera": {"driver": "sim", "options": {"stereo_baseline": 0.075}},
                  "obstacles": {"enabled": True, "source": source}})
    parse_config({"camera": {"driver": "oak"}, "obstacles": {"enabled": True, "source": source}})


@pytest.mark.parametrize("base, edit, says", [
    ("sentry-dynamixel", ("velocity_limit_rad_s: 6.0", "velocity_limit_rad_s: 3.0"),
     "robot.max_wheel_speed 6 rad/s is above what the drive lets a wheel turn"),
    ("sim", ("  model: pinhole\n", "  model: fisheye\n"), "the simulated camera renders pinhole cameras"),
])
def test_config_check_says_valid_only_for_a_configuration_a_run_takes(tmp_path, capsys, base, edit, says):
    """'vbnav config check' said "valid" for a configuration every run refused before a device opened (the
    refusals of the drive and camera as they are built: a wheel speed above the drive's own limit, a fisheye
    lens on the simulated camera). It now builds them as a run does (nothing is opened) and refuses the same."""
    from vbnav.control.config import CONFIG_DIR
    text = (CONFIG_DIR / f"{base}.yaml").read_text()
    assert text.count(edit[0]) == 1
    path = tmp_path / "robot.yaml"
    path.write_text(text.replace(*edit))
    assert main(["config", "check", "-c", str(path)]) == 2
    err = capsys.readouterr().err
    assert says in err and str(path) in err, err
    assert main(["run", "-c", str(path), "--camera", "--duration", "0.1", "--no-telemetry"]) == 2   # as a run
    assert says in capsys.readouterr().err
    assert main(["config", "check", "-c", base]) == 0


def test_a_turn_rate_the_wheels_cannot_reach_is_refused_at_load():
    """robot.max_angular_speed above what the wheels can turn the robot at (on the spot: 2 * max_wheel_speed *
    wheel_radius / wheel_separation) was accepted and the limiter cut every faster turn to the wheels' limit,
    as robot.max_linear_speed above max_wheel_speed * wheel_radius is refused. Refused at load, naming both."""
    from vbnav.control.runtime.interfaces import Twist
    from vbnav.control.runtime.kinematics import TwistLimiter
    with pytest.raises(ConfigError, match=r"robot.yaml: .*robot.max_angular_speed 10 rad/s exceeds what the wheels "
                                          r"can do \(2 \* max_wheel_speed \* wheel_radius / wheel_separation = "
                                          r"6.667 rad/s\)"):
        parse_config({"robot": {"max_angular_speed": 10.0}}, "robot.yaml")
    reach = 2 * 20.0 * 0.05 / 0.3
    cfg = parse_config({"robot": {"max_angular_speed": reach}})
    limiter = TwistLimiter.from_config(cfg.robot)
    limiter.max_dw = 1e9
    assert limiter.apply(Twist(0.0, 100.0), 0.01).w == pytest.approx(reach)     # the limit is reached
    small = parse_config({"robot": {"wheel_radius": 0.033, "max_wheel_speed": 6.0, "max_linear_speed": 0.18}})
    assert small.robot.max_angular_speed == pytest.approx(2 * 6.0 * 0.033 / 0.3)   # the default, cut
    assert parse_config(small.model_dump(mode="json")).robot.max_angular_speed == small.robot.max_angular_speed


@pytest.mark.parametrize("section, says", [
    ({"vslam": {"goto": {"final_turn_speed": 2.0}}},
     "vslam.goto.final_turn_speed 2 rad/s is above robot.max_angular_speed 1.5 rad/s"),
    ({"vslam": {"metric_scale": "odometry", "goto": {"init_creep_speed": 0.6}}},
     "vslam.goto.init_creep_speed 0.6 m/s is above robot.max_linear_speed 0.5 m/s"),
])
def test_goto_speeds_above_the_robots_limits_are_refused_at_load(section, says):
    """vslam.goto.final_turn_speed above robot.max_angular_speed, or init_creep_speed above max_linear_speed,
    was accepted and the limiter cut the command to the robot's limit without a word (as the cruise speeds
    were before they were refused). Refused at load naming both; the defaults are cut."""
    with pytest.raises(ConfigError, match=re.escape(says)):
        parse_config(section, "robot.yaml")
    slow = parse_config({"robot": {"max_angular_speed": 0.3, "max_linear_speed": 0.05},
                         "vslam": {"metric_scale": "odometry"}})
    assert slow.vslam.goto.final_turn_speed == 0.3 and slow.vslam.goto.init_creep_speed == 0.05
    assert parse_config(slow.model_dump(mode="json")).vslam.goto.final_turn_speed == 0.3    # loads back


@pytest.mark.parametrize("camera, says", [
    ({"stale_after_s": 0.08},
     "camera.stale_after_s 0.08 s is not above the time a frame may age before the next one comes, 0.097 s "
     "(the frame period 0.067 s at camera.rate_hz 15 Hz, plus sim.vision_latency_s 0.03 s)"),
    ({"rate_hz": 1.0}, "camera.stale_after_s 0.5 s is not above the time a frame may age before the next one "
                       "comes, 1.03 s"),
    ({"driver": "v4l2", "rate_hz": 30.0, "stale_after_s": 0.03, "options": {"source": "device"}},
     "0.033 s (the frame period 0.033 s at camera.rate_hz 30 Hz)"),
])
def test_a_stale_limit_every_frame_outlives_is_refused_at_load(camera, says):
    """camera.stale_after_s at or below the time between two frames (plus the simulated vision latency) was
    accepted, and every frame went stale before the next came: the simulated robot at 15 Hz with 0.08 s stood
    held for the whole run (camera_stale, never released). Refused at load naming the field, the frame rate and
    its setting; a limit above it loads."""
    with pytest.raises(ConfigError, match=re.escape(says)):
        parse_config({"camera": camera}, "robot.yaml")
    parse_config({"camera": {"stale_after_s": 0.1}})
    parse_config({"camera": {"stale_after_s": 0.08, "driver": "replay", "options": {"path": "rec"}}})  # rate unknown


def test_an_estimate_timeout_every_estimate_outlives_is_refused_at_load():
    """safety.estimate_timeout_s at or below the time between two frames (the stages' estimates come one a frame,
    plus the simulated vision latency) was accepted, and every estimate went stale before the next: sim_stereo's
    obstacle stop with 0.08 s held the robot for the whole run (obstacles_stale). Refused at load, naming it."""
    with pytest.raises(ConfigError, match=re.escape(
            "safety.estimate_timeout_s 0.08 s is not above the time a frame may age before the next one comes, "
            "0.097 s")):
        parse_config({"safety": {"estimate_timeout_s": 0.08}}, "robot.yaml")
    parse_config({"safety": {"estimate_timeout_s": 0.1}})


@pytest.mark.parametrize("section, says", [
    ({"vbc": {"approach_min_speed": 0.3}},
     "vbc.approach_min_speed 0.3 is not below vbc.cruise_speed 0.25: vbc.approach_gain would never apply"),
    ({"vslam": {"goto": {"min_drive_speed": 0.3}}},
     "vslam.goto.min_drive_speed 0.3 is not below vslam.goto.cruise_speed 0.3: vslam.goto.k_rho would never apply"),
    ({"vslam": {"goto": {"final_turn_min_speed": 0.5}}}, "vslam.goto.final_turn_min_speed 0.5 is not below "
     "vslam.goto.final_turn_speed 0.4: vslam.goto.final_turn_gain would never apply"),
])
def test_a_speed_floor_at_or_above_its_ceiling_is_refused_at_load(section, says):
    """The controllers' proportional speeds are held between a floor and a ceiling (kinematics.saturate: the
    ceiling wins where they cross). A floor written at or above its ceiling made the speed the ceiling all along:
    the repeat never slowed into the end of its route (approach_gain unused), the goto never slowed to its goal
    (k_rho) nor its final turn (final_turn_gain). Refused at load naming the floor, the ceiling and the gain."""
    from vbnav.control.runtime.kinematics import saturate
    assert saturate(1.5 * 0.01, 0.3, 0.25) == 0.25         # 1 cm from the end, still at cruise speed
    with pytest.raises(ConfigError, match=re.escape(says)):
        parse_config(section, "robot.yaml")


def test_a_camera_rate_above_the_loop_rate_on_the_simulated_clock_is_refused():
    """On the simulated clock the loop reads the simulated camera once a cycle (read(0)), and the newest due
    frame wins: camera.rate_hz 30 with loop.rate_hz 20 rendered 20 frames a second and dropped the others
    without a word. Refused at load naming both; the default is cut to the loop's rate (what is rendered), as
    config show prints it. In real time the vision thread reads every frame: accepted there."""
    with pytest.raises(ConfigError, match=r"robot.yaml: .*camera.rate_hz 30 Hz is above loop.rate_hz 20 Hz"):
        parse_config({"loop": {"rate_hz": 20}, "camera": {"rate_hz": 30}}, "robot.yaml")
    assert parse_config({"loop": {"rate_hz": 20}, "camera": {"rate_hz": 20}}).camera.rate_hz == 20
    assert parse_config({"loop": {"rate_hz": 20}, "camera": {"rate_hz": 30},
                         "sim": {"realtime": True}}).camera.rate_hz == 30
    slow = parse_config({"loop": {"rate_hz": 10}})
    assert slow.camera.rate_hz == 10
    assert parse_config(slow.model_dump(mode="json")).camera.rate_hz == 10       # loads back


def test_an_exponent_without_a_dot_is_a_number(tmp_path):
    """PyYAML (YAML 1.1) read ``1e-3`` as the text "1e-3"; the check then said 'write it without quotes' of a
    value that had none. It is the number YAML 1.2 and every other reader take it for; quoted it is refused."""
    cfg = load_config(write(tmp_path, "safety:\n  command_timeout_s: 25e-2\n"))
    assert cfg.safety.command_timeout_s == 0.25
    p = write(tmp_path, 'safety:\n  command_timeout_s: "25e-2"\n')
    with pytest.raises(ConfigError, match="expected a number, not the text '25e-2'"):
        load_config(p)
