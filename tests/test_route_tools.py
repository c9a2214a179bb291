"""``vbnav route list|info|plot|check`` on small routes written by the real RouteWriter, intact and damaged."""
from __future__ import annotations

import json
import math
import shutil
import zipfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from vbnav.control.cli import main
from vbnav.control.route import Keyframe, RouteError, RouteWriter
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.features import describe
from vbnav.vision.geometry import CameraMount, Pose2

W, H, N = 64, 48, 6


def keyframe(i: int, rng) -> Keyframe:
    """As teach writes one: the landmarks' descriptors are the ORB descriptors of its image at their pixels."""
    theta = 0.2 * i                                     # a gentle right turn
    image = rng.integers(0, 255, (H, W), dtype=np.uint8)
    pixels = rng.uniform((20, 20), (W - 20, H - 20), (N, 2)).astype(np.float32)   # away from ORB's border
    desc, described = describe(image, pixels)
    assert list(described) == list(range(N))
    return Keyframe(i, image, pixels, rng.normal(size=N),
                    rng.normal(size=N), desc, np.full(N, 0.5),
                    np.full(N, 0.01), np.arange(N, dtype=np.int64) + i, Pose2(math.sin(theta), math.cos(theta),
                                                                                 theta), 0.5 * i, 1000 * i)


def write_route(path, n=5, complete=True):
    rng = np.random.default_rng(len(str(path)))
    writer = RouteWriter(path, "testbot", PinholeCamera(W, H, 50.0, 50.0, 31.5, 23.5), CameraMount(0.2, 0.1, 0.0,
                                                                                                  0.05, 0.0))
    for i in range(n):
        writer.append(keyframe(i, rng))
    writer.close(complete=complete)
    return path


@pytest.fixture(scope="module")
def routes(tmp_path_factory):
    root = tmp_path_factory.mktemp("routes")
    write_route(root / "patrol")
    write_route(root / "half", n=3, complete=False)
    (root / "notes").mkdir()                             # not a route: not listed
    (root / ".patrol.partial-1").mkdir()                # a writer's scratch space: not listed
    return root


def test_list_shows_each_route_with_keyframes_length_and_completeness(routes, capsys):
    assert main(["route", "list", str(routes)]) == 0
    out = capsys.readouterr().out
    assert f"{routes}: 2 route(s)" in out
    assert [line.split()[:4] for line in out.splitlines()[2:]] == [["half", "3", "1.00", "m"],
                                                                  ["patrol", "5", "2.00", "m"]]
    assert "NO" in out.splitlines()[2] and "pinhole 64x48 fx 50" in out


def test_list_defaults_to_the_configurations_routes_dir(routes, tmp_path, capsys):
    cfg = tmp_path / "robot.yaml"
    cfg.write_text(f"controller: {{routes_dir: {routes}}}\n")
    assert main(["route", "list", "-c", str(cfg)]) == 0
    assert f"{routes}: 2 route(s)" in capsys.readouterr().out


def test_list_reports_an_unreadable_manifest_and_a_missing_folder(routes, tmp_path, capsys):
    shutil.copytree(routes / "patrol", tmp_path / "broken")
    (tmp_path / "broken" / "manifest.json").write_text("{not json")
    assert main(["route", "list", str(tmp_path)]) == 0
    assert "broken                   manifest.json unreadable (JSONDecodeError" in capsys.readouterr().out
    assert main(["route", "list", str(tmp_path / "nowhere")]) == 2
    assert main(["route", "list"]) == 2
    assert "give a folder of routes, or --config FILE" in capsys.readouterr().err
    # a folder and -c: the configuration was not read, a missing one accepted
    assert main(["route", "list", str(tmp_path), "-c", str(tmp_path / "nope.yaml")]) == 2
    assert f"or --config {tmp_path / 'nope.yaml'} for its controller.routes_dir, not both" in capsys.readouterr().err


def test_info(routes, capsys):
    assert main(["route", "info", str(routes / "half")]) == 0
    out = capsys.readouterr().out
    assert "robot:       testbot" in out and "keyframes:   3" in out and "length_m:    1.00" in out
    assert "complete:    no" in out and "camera:      pinhole 64x48, fx 50.0" in out
    assert f"landmarks:   {N} / {N} / {N} per keyframe" in out and "pitch 2.9 deg" in out
    assert "note:        the route is incomplete" in out


def test_info_prints_the_calibration_in_one_line(tmp_path, capsys):
    rng = np.random.default_rng(3)
    cal = {"file": "/etc/vbnav/camera_info.yaml", "sha256": "0123456789abcdef" * 4, "format": "ros",
           "model": "pinhole", "width": W, "height": H, "fx": 50.0, "fy": 50.5, "cx": 31.5, "cy": 23.5,
           "distortion": [-0.1, 0.01, 0.0, 0.0, 0.0], "baseline": None}
    writer = RouteWriter(tmp_path / "r", "testbot", PinholeCamera(W, H, 50.0, 50.5, 31.5, 23.5),
                         CameraMount(0.2, 0.1, 0.0, 0.05, 0.0), calibration=cal)
    writer.append(keyframe(0, rng))
    writer.close(complete=True)
    assert main(["route", "info", str(tmp_path / "r")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("calibration:"))
    assert line == ("calibration: /etc/vbnav/camera_info.yaml (ros, sha256 0123456789ab); pinhole 64x48; "
                    "fx 50.00 fy 50.50 cx 31.50 cy 23.50 px; distortion [-0.1, 0.01, 0, 0, 0]"), line


def test_plot_writes_a_png_beside_the_route_or_where_asked(routes, tmp_path, capsys):
    route = shutil.copytree(routes / "patrol", tmp_path / "patrol")
    assert main(["route", "plot", str(route)]) == 0
    image = cv2.imread(str(tmp_path / "patrol.png"))
    assert image is not None and image.shape[0] > 300 and image.std() > 10
    assert main(["route", "plot", str(route), "--out", str(tmp_path / "no" / "p.png")]) == 2
    assert "--out" in capsys.readouterr().err


def test_check_an_intact_route(routes, capsys):
    assert main(["route", "check", str(routes / "patrol")]) == 0
    assert capsys.readouterr().out.strip().endswith("intact, 5 keyframes, complete")
    assert main(["route", "check", str(routes / "half")]) == 0
    out = capsys.readouterr().out
    assert "incomplete (teaching was interrupted)" in out and "note: the route is incomplete" in out


def damaged_copy(routes, tmp_path):
    return shutil.copytree(routes / "patrol", tmp_path / "patrol")


def flip(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_check_finds_a_png_chunk_that_fails_its_crc(routes, tmp_path, capsys):
    route = damaged_copy(routes, tmp_path)
    png = route / "kf_00002.png"
    flip(png, png.read_bytes().index(b"IDAT") + 10)
    assert main(["route", "check", str(route)]) == 1
    out = capsys.readouterr().out
    assert "damaged: keyframes[2]: kf_00002.png: CRC-32 mismatch in chunk 'IDAT'" in out and "DAMAGED" in out


def test_check_finds_landmark_data_that_fails_its_crc(routes, tmp_path, capsys):
    route = damaged_copy(routes, tmp_path)
    npz = route / "kf_00001.npz"
    with zipfile.ZipFile(npz) as z:
        info = z.getinfo("alpha.npy")
    flip(npz, info.header_offset + 30 + len(info.filename) + len(info.extra) + 130)   # inside the array data
    assert main(["route", "check", str(route)]) == 1
    assert "kf_00001.npz: CRC-32 mismatch in member 'alpha.npy'" in capsys.readouterr().out


def test_check_finds_a_manifest_that_disagrees_with_the_files(routes, tmp_path, capsys):
    route = damaged_copy(routes, tmp_path)
    m = json.loads((route / "manifest.json").read_text())
    m["keyframes"][3]["odom"][0] += 0.5
    (route / "manifest.json").write_text(json.dumps(m))
    assert main(["route", "check", str(route)]) == 1
    assert "keyframes[3]: the manifest's odom" in capsys.readouterr().out
    (route / "kf_00004.npz").unlink()
    assert main(["route", "check", str(route)]) == 1
    assert "kf_00004.npz: missing keyframe file" in capsys.readouterr().out


def test_check_notes_leftovers_and_refuses_what_is_not_a_route(routes, tmp_path, capsys):
    route = damaged_copy(routes, tmp_path)
    shutil.copy(route / "kf_00004.png", route / "kf_00005.png")        # written when teaching stopped
    (route / "manifest.json.tmp").write_text("")
    assert main(["route", "check", str(route)]) == 0
    out = capsys.readouterr().out
    assert "files not in the manifest (a keyframe being written when teaching stopped): kf_00005.png" in out
    assert "temporary files an interrupted writer left: manifest.json.tmp" in out
    assert main(["route", "check", str(tmp_path / "nothing")]) == 2
    assert main(["route", "check", str(routes / "notes")]) == 2
    assert "manifest.json: missing" in capsys.readouterr().err


def test_check_and_info_say_what_is_wrong_with_non_numbers_in_the_manifest(routes, tmp_path, capsys):
    """A manifest's odom or distance that is not a number, or calibration fields that are not numbers, were
    tracebacks of route check and route info; now check reports the damage and info shows them as written."""
    route = damaged_copy(routes, tmp_path)
    m = json.loads((route / "manifest.json").read_text())
    m["keyframes"][2].update(odom="abc", distance="x")
    m["calibration"] = {"file": "cam.yaml", "distortion": ["a"], "baseline": "q"}
    (route / "manifest.json").write_text(json.dumps(m))
    assert main(["route", "check", str(route)]) == 1
    out = capsys.readouterr().out
    assert "keyframes[2]: the manifest's odom abc differs" in out
    assert "keyframes[2]: the manifest's distance 'x' differs" in out
    assert main(["route", "info", str(route)]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("calibration:"))
    assert "distortion [['a']]" in line and "baseline 'q'" in line, line


@pytest.mark.parametrize("complete", [True, False])
def test_check_fails_a_route_repeat_refuses(tmp_path, capsys, complete):
    """A route of 0 keyframes loads (every file is intact), and route check called it 'intact ... complete'
    with exit 0 while vbnav repeat refuses it: check fails it with repeat's own reason."""
    route = write_route(tmp_path / "empty", n=0, complete=complete)
    assert main(["repeat", "--path", str(route)]) == 2
    refusal = capsys.readouterr().err
    assert "the route has no keyframes" in refusal
    assert main(["route", "check", str(route)]) == 1
    out = capsys.readouterr().out
    assert "intact" not in out and "vbnav repeat refuses it: the route has no keyframes" in out, out


def test_list_does_not_call_a_complete_of_another_type_complete(tmp_path, capsys):
    """A hand-edited "complete": "false" was listed as complete (bool of a non-empty string) while every
    command that loads the route refuses it: the list says what is wrong with it instead."""
    import json as _json
    route = write_route(tmp_path / "edited", n=2)
    m = _json.loads((route / "manifest.json").read_text())
    m["complete"] = "false"
    (route / "manifest.json").write_text(_json.dumps(m))
    assert main(["route", "list", str(tmp_path)]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert "edited" in line and "complete: expected true or false, got 'false'" in line and " yes " not in line


def test_a_manifest_key_given_twice_is_refused(tmp_path, capsys):
    """A hand-edited manifest with "complete" twice loaded with the last one: refused naming the key."""
    route = write_route(tmp_path / "twice", n=2, complete=False)
    text = (route / "manifest.json").read_text()
    (route / "manifest.json").write_text(text.rstrip()[:-1] + ', "complete": true}')
    assert main(["repeat", "--path", str(route)]) == 2
    assert "manifest.json: not valid JSON (duplicate key 'complete')" in capsys.readouterr().err


def test_list_shows_a_manifest_key_given_twice_as_that_routes_error(tmp_path, capsys):
    """route list read manifests with plain json.loads: a "complete" given twice was listed with the last one
    ("yes") while repeat, info and check refuse the route naming the duplicate key."""
    route = write_route(tmp_path / "twice", n=2, complete=False)
    text = (route / "manifest.json").read_text()
    (route / "manifest.json").write_text(text.rstrip()[:-1] + ', "complete": true}')
    write_route(tmp_path / "good", n=2)
    assert main(["route", "list", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    twice = next(x for x in lines if x.split()[:1] == ["twice"])
    assert "duplicate key 'complete'" in twice and " yes " not in twice, twice
    assert " yes" in next(x for x in lines if x.split()[:1] == ["good"])


def test_a_route_whose_manifest_gives_a_key_twice_is_not_offered_for_transfer(tmp_path):
    """route_transfer.route_files (push, pull, the robot's file listing) read the manifest with plain json.loads:
    a route every loader refuses (a key given twice) was listed and sent, to be refused only after the transfer."""
    from vbnav.control.comms.route_transfer import route_files
    route = write_route(tmp_path / "twice", n=2, complete=False)
    text = (route / "manifest.json").read_text()
    (route / "manifest.json").write_text(text.rstrip()[:-1] + ', "complete": true}')
    with pytest.raises(RouteError, match="duplicate key 'complete'"):
        route_files(route)


def test_a_keyframe_image_swapped_with_another_keyframes_is_damage(tmp_path, capsys):
    """Two keyframe images swapped pass every checksum and load; the descriptors recomputed at the stored
    pixels no longer match the stored ones, and check names both keyframes."""
    route = write_route(tmp_path / "r")
    a, b = route / "kf_00001.png", route / "kf_00003.png"
    data = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(data)
    assert main(["route", "check", str(route)]) == 1
    out = capsys.readouterr().out
    assert "DAMAGED" in out and "keyframes[1]: kf_00001.png: the ORB descriptors at" in out, out
    assert "keyframes[3]: kf_00003.png" in out and "keyframes[2]" not in out and "keyframes[0]" not in out, out


def test_descriptors_a_few_bits_off_are_the_same_patch(tmp_path):
    """Another OpenCV build may compute an ORB descriptor a few bits differently from the one teach stored: that
    is the same image, not damage (check must not call a route taught on the robot damaged on a laptop)."""
    from vbnav.control.route import load_route
    from vbnav.control.route_tools import ORB_SAME_PATCH_BITS, image_problem
    route = load_route(write_route(tmp_path / "r"))
    kf = route.keyframes[1]
    assert image_problem(kf) is None
    rng = np.random.default_rng(0)
    near = kf.descriptors.copy()
    for d in near:                                    # flip 8 of 256 bits of every descriptor
        for bit in rng.choice(256, 8, replace=False):
            d[bit // 8] ^= np.uint8(1 << (bit % 8))
    assert image_problem(replace(kf, descriptors=near)) is None
    far = rng.integers(0, 256, kf.descriptors.shape, dtype=np.uint8)  # unrelated patches: ~128 bits apart
    assert ORB_SAME_PATCH_BITS < 100 and image_problem(replace(kf, descriptors=far)) is not None


def test_check_with_a_configuration_refuses_what_repeat_with_it_refuses(tmp_path, capsys):
    """route check took no -c: a route taught with another camera or mount than the robot's configuration was
    called intact, and vbnav repeat -c with that configuration refused it. With -c, check says repeat's own
    refusal (check_route_camera, check_route_mount) and exits 1; a configuration of the route's camera and mount
    passes."""
    import yaml
    from vbnav.control.config import load_config
    route = write_route(tmp_path / "patrol")
    base = yaml.safe_load(Path(load_config("sim").source).read_text())
    cam = {"model": "pinhole", "width": W, "height": H, "fx": 50.0, "fy": 50.0, "cx": 31.5, "cy": 23.5,
           "distortion": [], "mount": {"height": 0.2, "forward": 0.1, "lateral": 0.0,
                                       "pitch_deg": math.degrees(0.05), "yaw_deg": 0.0}}
    cases = {"same": (cam, None), "lens": ({**cam, "fx": 60.0, "fy": 60.0}, "other intrinsics"),
             "mount": ({**cam, "mount": {**cam["mount"], "height": 0.25}}, "camera.mount")}
    for name, (camera, why) in cases.items():
        cfg = tmp_path / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump({**base, "camera": {**base["camera"], **camera}}))
        code = main(["route", "check", "-c", str(cfg), str(route)])
        out = capsys.readouterr().out
        if why is None:
            assert code == 0 and out.strip().endswith("intact, 5 keyframes, complete"), out
            continue
        assert code == 1 and f"vbnav repeat -c {cfg} refuses it" in out and why in out, out
        assert main(["repeat", "-c", str(cfg), "--path", str(route)]) == 2          # the same refusal
        assert why in capsys.readouterr().err
