"""The route loader refuses what would mislead a repeat, naming the keyframe; an incomplete route is announced."""
from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from vbnav.control import route as route_mod
from vbnav.control.route import RouteError, RouteWriter, load_route
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount

from test_route import CAM, MOUNT, make_kf, write_route


def _edit_manifest(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m.update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


def _edit_npz(path, **changes):
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data.update(changes)
    np.savez(path, **data)


@pytest.mark.parametrize("version,why", [(0, "not a route version"), (-7, "not a route version"),
                                         (999, "newer than this vbnav reads")])
def test_version_out_of_range(tmp_path, rng, version, why):
    write_route(tmp_path / "r", rng)
    _edit_manifest(tmp_path / "r", version=version)
    with pytest.raises(RouteError, match=f"version {version} is {why}"):
        load_route(tmp_path / "r")


@pytest.mark.parametrize("load_images", [True, False])
def test_image_size_must_match_the_camera(tmp_path, rng, load_images, monkeypatch):
    write_route(tmp_path / "r", rng)
    cv2.imwrite(str(tmp_path / "r" / "kf_00001.png"), np.zeros((47, 64), np.uint8))
    with pytest.raises(RouteError, match=r"kf_00001.png: keyframes\[1\] image is 64x47, the route's camera is 64x48"):
        load_route(tmp_path / "r", load_images=load_images)
    other = PinholeCamera(32, 24, 20.0, 20.0, 15.5, 11.5)
    with monkeypatch.context() as m:    # the writer refuses the pixels outside `other`: written as they are
        m.setattr(route_mod, "_check_pixels", lambda *a: None)
        with RouteWriter(tmp_path / "o", "sim", other, MOUNT) as w:      # images of CAM, manifest of another camera
            w.append(make_kf(rng, 0))
    with pytest.raises(RouteError, match=r"keyframes\[0\] image is 64x48, the route's camera is 32x24"):
        load_route(tmp_path / "o", load_images=load_images)


@pytest.mark.parametrize("field,value", [("alpha", np.nan), ("beta", np.inf), ("pixels", np.nan),
                                         ("inv_height", np.inf), ("inv_height_var", np.nan),
                                         ("inv_height_var", -1.0)])
def test_non_finite_landmarks_name_the_keyframe(tmp_path, rng, field, value):
    write_route(tmp_path / "r", rng)
    npz = tmp_path / "r" / "kf_00002.npz"
    with np.load(npz) as z:
        a = z[field].copy()
    a[3] = value
    _edit_npz(npz, **{field: a})
    with pytest.raises(RouteError, match=r"kf_00002.npz: keyframes\[2\]"):
        load_route(tmp_path / "r")


def test_unknown_inverse_heights_are_allowed(tmp_path, rng):
    write_route(tmp_path / "r", rng)
    npz = tmp_path / "r" / "kf_00001.npz"
    _edit_npz(npz, inv_height=np.full(20, np.nan), inv_height_var=np.full(20, np.inf))
    assert len(load_route(tmp_path / "r")) == 3


def test_copies_of_one_keyframe_and_going_back_are_refused(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(route_mod, "_check_step", lambda *a: None)     # the writer refuses them: written anyway
    kf = make_kf(rng, 0)
    with RouteWriter(tmp_path / "copies", "sim", CAM, MOUNT) as w:
        for _ in range(62):
            w.append(kf)
    monkeypatch.undo()
    with pytest.raises(RouteError, match=r"keyframes\[1\]: along-route distance 0.000 m repeats keyframes\[0\]"):
        load_route(tmp_path / "copies")
    monkeypatch.setattr(route_mod, "_check_step", lambda *a: None)
    kfs = [make_kf(rng, i) for i in range(4)]
    kfs[3].distance = 0.7
    with RouteWriter(tmp_path / "back", "sim", CAM, MOUNT) as w:
        for k in kfs:
            w.append(k)
    monkeypatch.undo()
    with pytest.raises(RouteError, match=r"keyframes\[3\]: along-route distance 0.700 m is less than keyframes\[2\]"):
        load_route(tmp_path / "back")


def test_a_turn_on_the_spot_keeps_its_distance(tmp_path, rng):
    a, b = make_kf(rng, 0), make_kf(rng, 1)
    b.distance, b.odom = a.distance, type(a.odom)(a.odom.x, a.odom.z, a.odom.theta + 0.5)
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT) as w:
        w.append(a)
        w.append(b)
    assert len(load_route(tmp_path / "r")) == 2


def test_repeat_of_an_incomplete_route_warns_how_much_exists(tmp_path):
    cam = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
    rng = np.random.default_rng(1)
    w = RouteWriter(tmp_path / "r", "sim", cam, CameraMount(0.25, 0.1, 0.0, 0.0, 0.0))
    for i in range(3):
        kf = make_kf(rng, i)
        kf.image = rng.integers(0, 255, (480, 640), dtype=np.uint8)
        w.append(kf)
    w.close(complete=False)
    assert load_route(tmp_path / "r").incomplete_note().startswith("the route is incomplete")
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "repeat", "--path", str(tmp_path / "r"),
                        "--duration", "0.1"], capture_output=True, text=True, timeout=120)
    assert "warning" in r.stderr and "incomplete" in r.stderr and "3 keyframes over 1.00 m exist" in r.stderr, r.stderr


def test_descriptors_of_another_type_are_refused(tmp_path, rng):
    """ORB descriptors are uint8: uint16 ones passed (kind 'u') and the repeat's matcher raised an OpenCV
    assertion at that keyframe; ``vbnav route check`` called the route intact."""
    write_route(tmp_path / "r", rng)
    npz = tmp_path / "r" / "kf_00001.npz"
    with np.load(npz) as z:
        d = z["descriptors"].astype(np.uint16)
    _edit_npz(npz, descriptors=d)
    with pytest.raises(RouteError, match=r"kf_00001.npz: array 'descriptors' has shape \(20, 32\) dtype uint16, "
                                         r"expected shape \(20, 32\) of dtype uint8"):
        load_route(tmp_path / "r")


@pytest.mark.parametrize("load_images", [True, False])
@pytest.mark.parametrize("image,what", [(np.full((48, 64), 5000, np.uint16), "16-bit"),
                                        (np.zeros((48, 64, 4), np.uint8), "4 channels")])
def test_keyframe_image_of_another_type_is_refused(tmp_path, rng, load_images, image, what):
    """A keyframe image is 8-bit grey or colour: a 16-bit (or RGBA) PNG of the right size loaded, route check
    called the route intact and the repeat's guided search (KLT) raised an OpenCV assertion there."""
    write_route(tmp_path / "r", rng)
    cv2.imwrite(str(tmp_path / "r" / "kf_00001.png"), image)
    with pytest.raises(RouteError, match=r"kf_00001.png: keyframes\[1\] image is .*expected an 8-bit grey or "
                                         r"colour image"):
        load_route(tmp_path / "r", load_images=load_images)


def test_a_manifest_that_pairs_one_keyframe_s_image_with_another_s_landmarks_is_refused(tmp_path, rng):
    """keyframes[1] listing kf_00002.png with kf_00001.npz (images swapped in the manifest) loaded: the guided
    search then tracked kf_00001's landmark pixels in kf_00002's image. An index that is not the entry's
    position was taken as well."""
    write_route(tmp_path / "r", rng)
    m = json.loads((tmp_path / "r" / "manifest.json").read_text())
    kfs = m["keyframes"]
    kfs[1]["image"], kfs[2]["image"] = kfs[2]["image"], kfs[1]["image"]
    _edit_manifest(tmp_path / "r", keyframes=kfs)
    with pytest.raises(RouteError, match=r"manifest.json: keyframes\[1\]: image 'kf_00002.png' and landmarks "
                                         r"'kf_00001.npz' are not the files of one keyframe"):
        load_route(tmp_path / "r")
    kfs[1]["image"], kfs[2]["image"] = kfs[2]["image"], kfs[1]["image"]
    kfs[2]["index"] = 1
    _edit_manifest(tmp_path / "r", keyframes=kfs)
    with pytest.raises(RouteError, match=r"manifest.json: keyframes\[2\]: index 1, expected 2"):
        load_route(tmp_path / "r")


@pytest.mark.parametrize("model,dist", [("fisheye", [0.1, 0.0, 0.0, 0.0, 0.2]), ("pinhole", [0.1, 0.0, 0.0])])
def test_a_camera_with_a_distortion_of_another_length_is_refused(tmp_path, rng, model, dist):
    """A fisheye has k1..k4 and a pinhole 4, 5, 8, 12 or 14 OpenCV coefficients: a fifth fisheye coefficient
    was silently dropped, three pinhole ones failed OpenCV's undistortion at the first frame of a repeat."""
    write_route(tmp_path / "r", rng)
    m = json.loads((tmp_path / "r" / "manifest.json").read_text())
    _edit_manifest(tmp_path / "r", camera={**m["camera"], "model": model, "dist": dist})
    with pytest.raises(RouteError, match=rf"manifest.json: camera: dist: {model} expects .*, got {len(dist)}"):
        load_route(tmp_path / "r")


def test_landmark_pixels_outside_the_image_are_refused(tmp_path, rng):
    """A landmark's pixel is where it was seen in the keyframe image: pixels 5000 px off the 64x48 image
    loaded and route check called the route intact (the guided search then tracked nothing from them)."""
    write_route(tmp_path / "r", rng)
    npz = tmp_path / "r" / "kf_00001.npz"
    with np.load(npz) as z:
        px = z["pixels"].copy()
    px[4] = (70.0, 10.0)
    _edit_npz(npz, pixels=px)
    with pytest.raises(RouteError, match=r"kf_00001.npz: keyframes\[1\]: landmark 4's pixel \(70.0, 10.0\) is "
                                         r"outside the 64x48 image"):
        load_route(tmp_path / "r")


def test_a_keyframe_the_route_could_not_load_is_refused_when_written(tmp_path, rng):
    """A keyframe with a NaN odometry pose (or a landmark pixel) was written, and the whole route then failed
    to load at the repeat ('odom must be 3 finite numbers'): every keyframe taught was unusable. The writer
    now refuses it, the route keeps the keyframes before it."""
    with pytest.raises(RouteError, match=r"kf_00001.npz: 'odom' must be 3 finite numbers"):
        with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT) as w:
            w.append(make_kf(rng, 0))
            bad = make_kf(rng, 1)
            bad.odom = type(bad.odom)(float("nan"), 0.0, 0.0)
            w.append(bad)
    r = load_route(tmp_path / "r")
    assert len(r) == 1 and not r.complete
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["kf_00000.npz", "kf_00000.png", "manifest.json"]


def test_a_keyframe_that_goes_back_or_lies_outside_the_image_is_refused_when_written(tmp_path, rng):
    """A keyframe at a shorter along-route distance than the one before (or a copy of it), or with landmark
    pixels outside the camera's image, was written and made the whole route unloadable."""
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT) as w:
        w.append(make_kf(rng, 0))
        w.append(make_kf(rng, 1))
        back = make_kf(rng, 2)
        back.distance = 0.2
        with pytest.raises(RouteError, match=r"keyframes\[2\]: along-route distance 0.200 m is less than "
                                             r"keyframes\[1\]'s 0.500 m"):
            w.append(back)
        off = make_kf(rng, 2)
        off.pixels[3] = (500.0, 10.0)
        with pytest.raises(RouteError, match=r"kf_00002.npz: keyframes\[2\]: landmark 3's pixel \(500.0, 10.0\) "
                                             r"is outside the 64x48 image"):
            w.append(off)
        w.append(make_kf(rng, 2))
    assert len(load_route(tmp_path / "r")) == 3


def test_a_keyframe_farther_from_the_one_before_than_the_distance_driven_between_them_is_refused(tmp_path, rng):
    """A repeat follows the keyframes' odometry poses; teach adds up the odometry it drives into the along-route
    distance, so one keyframe is never farther from the one before than that distance grew (a chord is no longer
    than its arc). A keyframe whose odometry says otherwise (its landmark file from another route, a damaged
    one) was loaded, and the repeat drove towards where it says. Refused at load, and by the writer."""
    import math

    from vbnav.vision.geometry import Pose2
    kfs = [make_kf(rng, i) for i in range(4)]
    kfs[2].odom = Pose2(5.0, 3.0, 0.1)                       # 5.37 m from keyframes[1], distance 0.5 m on
    with pytest.raises(RouteError, match=r"keyframes\[2\]: odometry 5.370 m from keyframes\[1\]'s, beyond the "
                                         r"0.500 m of along-route distance between them"):
        with RouteWriter(tmp_path / "w", "sim", CAM, MOUNT) as w:
            for k in kfs:
                w.append(k)
    _edit_npz(tmp_path / "w" / "kf_00001.npz", odom=np.array([5.0, 3.0, 0.1]))    # written, then damaged
    with pytest.raises(RouteError, match=r"keyframes\[1\]: odometry 5.831 m from keyframes\[0\]'s"):
        load_route(tmp_path / "w")
    ok = [make_kf(rng, i) for i in range(3)]                 # chord == arc (a straight line) is a step
    for i, k in enumerate(ok):
        k.odom, k.distance = Pose2(0.3 * i, 0.4 * i, 0.0), 0.5 * i
    with RouteWriter(tmp_path / "ok", "sim", CAM, MOUNT) as w:
        for k in ok:
            w.append(k)
    assert math.isclose(load_route(tmp_path / "ok").length, 1.0)


def test_a_keyframe_without_landmarks_is_refused(tmp_path, rng):
    """Teach writes a keyframe only from a frame with vbc.min_keyframe_landmarks tracks; one without any
    landmark (a damaged file) was loaded and written, and the repeat drove past it blind (two in a row
    stopped it). Refused at load and by the writer, naming the keyframe and the file."""
    from dataclasses import replace
    z = np.zeros(0)
    empty = replace(make_kf(rng, 1), pixels=np.zeros((0, 2), np.float32), alpha=z, beta=z, inv_height=z,
                    inv_height_var=z, descriptors=np.zeros((0, 32), np.uint8), track_ids=np.zeros(0, np.int64))
    with pytest.raises(RouteError, match=r"kf_00001.npz: keyframes\[1\] has no landmarks"):
        with RouteWriter(tmp_path / "w", "sim", CAM, MOUNT) as w:
            for k in (make_kf(rng, 0), empty, make_kf(rng, 2)):
                w.append(k)
    write_route(tmp_path / "r", rng)
    _edit_npz(tmp_path / "r" / "kf_00001.npz", **{k: getattr(empty, k) for k in
                                                  ("pixels", "alpha", "beta", "inv_height", "inv_height_var",
                                                   "descriptors", "track_ids")})
    m = json.loads((tmp_path / "r" / "manifest.json").read_text())
    m["keyframes"][1]["n_landmarks"] = 0
    (tmp_path / "r" / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(RouteError, match=r"kf_00001.npz: keyframes\[1\] has no landmarks"):
        load_route(tmp_path / "r")
