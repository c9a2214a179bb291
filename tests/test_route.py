"""Route directory: round trip, validation errors, crash safety."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from vbnav.control import route as route_mod
from vbnav.control.route import Keyframe, RouteError, RouteWriter, load_route, stray_temp_files
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.features import describe
from vbnav.vision.geometry import CameraMount, Pose2

CAM = PinholeCamera(64, 48, 40.0, 40.0, 31.5, 23.5, (0.01, -0.002, 0.0, 0.0))
MOUNT = CameraMount(0.25, 0.1, 0.0, 0.05, 0.0)


def make_kf(rng, i, n=20):
    """As teach writes one: the landmarks' descriptors are the ORB descriptors of its image at their pixels."""
    image = rng.integers(0, 255, (48, 64), dtype=np.uint8)
    pixels = rng.uniform((20, 20), (44, 28), (n, 2)).astype(np.float32)    # away from ORB's border
    desc, described = describe(image, pixels)
    assert list(described) == list(range(n))
    return Keyframe(i, image, pixels,
                    rng.normal(0, 0.3, n), rng.normal(0, 0.2, n), desc,
                    rng.normal(0, 1, n), rng.random(n), np.arange(n, dtype=np.int64) + 10 * i,
                    Pose2(0.48 * i, 0.1 * i, 0.05 * i), 0.5 * i, 1000 * i)


def write_route(path, rng, n=3):
    kfs = [make_kf(rng, i) for i in range(n)]
    with RouteWriter(path, "sim", CAM, MOUNT) as w:
        for kf in kfs:
            w.append(kf)
    return kfs


def test_round_trip(tmp_path, rng):
    kfs = write_route(tmp_path / "r", rng)
    r = load_route(tmp_path / "r")
    assert r.complete and r.robot == "sim" and len(r) == 3 and r.camera == CAM and r.mount == MOUNT
    for a, b in zip(kfs, r.keyframes):
        np.testing.assert_array_equal(a.image, b.image)
        for k in ("pixels", "alpha", "beta", "descriptors", "inv_height", "inv_height_var", "track_ids"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        assert a.odom == b.odom and a.distance == b.distance and a.stamp_ns == b.stamp_ns
    m = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert m["format"] == "vbnav-route" and m["version"] == 1 and len(m["keyframes"]) == 3


def test_refuses_non_empty_directory(tmp_path, rng):
    write_route(tmp_path / "r", rng)
    with pytest.raises(RouteError, match="not empty"):
        RouteWriter(tmp_path / "r", "sim", CAM, MOUNT)


@pytest.mark.parametrize("case, match", [
    ("missing_dir", "does not exist"),
    ("no_manifest", "manifest.json: missing"),
    ("bad_json", "not valid JSON"),
    ("foreign", "expected 'vbnav-route'"),
    ("newer", "newer than this vbnav reads"),
    ("missing_kf", "kf_00001.npz: missing keyframe file"),
    ("truncated_npz", "kf_00002.npz: corrupt or truncated"),
    ("bad_array", "kf_00000.npz: array 'beta' has shape"),
    ("bad_png", "kf_00001.png: not a readable PNG"),
    # these were tracebacks (TypeError, ValueError, RuntimeError, RecursionError) or loaded without a word
    ("n_landmarks_word", r"kf_00001.npz: has 20 landmarks, manifest keyframes\[1\].n_landmarks says 'abc'"),
    ("distance_array", r"kf_00001.npz: 'distance' has shape \(2,\) dtype float64, expected one number"),
    ("stamp_word", r"kf_00001.npz: 'stamp_ns' has shape \(\) dtype <U3, expected one integer"),
    ("odom_words", r"kf_00001.npz: 'odom' has shape \(3,\) dtype <U1, expected 3 numbers"),
    ("alpha_scalar", r"kf_00001.npz: array 'alpha' has shape \(\), expected one value per landmark"),
    ("nan_focal", r"manifest.json: camera: expected .*fx, fy > 0.*; got 64x48 fx nan"),
    ("negative_focal", r"manifest.json: camera: expected .*; got 64x48 fx -40.0"),
    ("nan_mount", r"manifest.json: mount: expected finite numbers, got \{'height': nan"),
    ("complete_word", "manifest.json: complete: expected true or false, got 'false'"),
    ("png_link_loop", r"kf_00001.png: a symbolic link loop, expected a keyframe file"),
    ("deep_json", "manifest.json: not a route manifest"),
])
def test_clear_errors(tmp_path, rng, case, match):
    d = tmp_path / "r"
    write_route(d, rng)
    mpath = d / "manifest.json"
    m = json.loads(mpath.read_text())
    if case == "missing_dir":
        d = tmp_path / "nope"
    elif case == "no_manifest":
        mpath.unlink()
    elif case == "bad_json":
        mpath.write_text("{not json")
    elif case == "foreign":
        m["format"] = "someone-else"
        mpath.write_text(json.dumps(m))
    elif case == "newer":
        m["version"] = 99
        mpath.write_text(json.dumps(m))
    elif case == "missing_kf":
        (d / "kf_00001.npz").unlink()
    elif case == "truncated_npz":
        p = d / "kf_00002.npz"
        p.write_bytes(p.read_bytes()[:200])
    elif case == "bad_array":
        z = dict(np.load(d / "kf_00000.npz"))
        z["beta"] = z["beta"][:-1]
        np.savez(d / "kf_00000.npz", **z)
    elif case == "bad_png":
        (d / "kf_00001.png").write_bytes(b"garbage")
    elif case in ("distance_array", "stamp_word", "odom_words", "alpha_scalar"):
        z = dict(np.load(d / "kf_00001.npz"))
        key, value = {"distance_array": ("distance", np.array([0.5, 1.0])),
                      "stamp_word": ("stamp_ns", np.array("abc")),
                      "odom_words": ("odom", np.array(["a", "b", "c"])),
                      "alpha_scalar": ("alpha", np.float64(0.1))}[case]
        z[key] = value
        np.savez(d / "kf_00001.npz", **z)
    elif case == "png_link_loop":
        (d / "kf_00001.png").unlink()
        os.symlink(d / "kf_00001.png", d / "kf_00001.png")
    elif case == "deep_json":
        mpath.write_text("[" * 100000 + "]" * 100000)
    else:
        edit = {"n_landmarks_word": lambda: m["keyframes"][1].update(n_landmarks="abc"),
                "nan_focal": lambda: m["camera"].update(fx=float("nan")),
                "negative_focal": lambda: m["camera"].update(fx=-40.0),
                "nan_mount": lambda: m["mount"].update(height=float("nan")),
                "complete_word": lambda: m.update(complete="false")}[case]
        edit()
        mpath.write_text(json.dumps(m))
    with pytest.raises(RouteError, match=match):
        load_route(d)


def test_interrupted_write_leaves_a_valid_route(tmp_path, rng, monkeypatch):
    """A crash while writing keyframe 2 (its rename fails) keeps keyframes 0 and 1 loadable."""
    d = tmp_path / "r"
    w = RouteWriter(d, "sim", CAM, MOUNT)
    w.append(make_kf(rng, 0))
    w.append(make_kf(rng, 1))
    real_replace = os.replace

    def crash_on_npz(src, dst):
        if str(dst).endswith("kf_00002.npz"):
            raise OSError("simulated power cut")
        return real_replace(src, dst)

    monkeypatch.setattr(route_mod.os, "replace", crash_on_npz)
    # A power cut also stops the writer's clean-up: its temporary file stays behind.
    monkeypatch.setattr(Path, "unlink", lambda self, missing_ok=False: None)
    with pytest.raises(OSError, match="power cut"):
        w.append(make_kf(rng, 2))
    monkeypatch.undo()
    r = load_route(d)
    assert len(r) == 2 and not r.complete
    stray = [p.name for p in stray_temp_files(d)]
    assert len(stray) == 1 and stray[0].startswith(".kf_00002.npz.") and stray[0].endswith(".tmp"), stray


def test_half_written_manifest_temp_is_ignored(tmp_path, rng):
    d = tmp_path / "r"
    write_route(d, rng, n=2)
    (d / "manifest.json.tmp").write_text('{"format": "vbnav-ro')     # killed mid-write
    assert len(load_route(d)) == 2


def test_exception_inside_writer_marks_incomplete(tmp_path, rng):
    with pytest.raises(RuntimeError):
        with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT) as w:
            w.append(make_kf(rng, 0))
            raise RuntimeError("teleop lost")
    r = load_route(tmp_path / "r")
    assert len(r) == 1 and not r.complete
