"""Recorded sequences damaged the way real copies are: each is read correctly or refused naming the file and
what was expected (never a silent wrong answer)."""
from __future__ import annotations

import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from vbnav.drivers.datasets import DatasetError, open_dataset

sys.path.insert(0, str(Path(__file__).parent))
from room_view import room_view  # noqa: E402


def _room(shared_data: Path, tmp_path: Path) -> Path:
    """A TUM view of room_rgbd5 whose depth files are copies (not links) that a test may damage."""
    view = room_view(shared_data / "room_rgbd5", tmp_path / "room")
    for p in view.glob("depth_*.pgm"):
        data = p.read_bytes()
        p.unlink()
        p.write_bytes(data)
    return view


def test_an_8_bit_depth_image_is_refused_not_read_as_centimetres(shared_data, tmp_path):
    """A depth image saved 8-bit (a viewer's export) was scaled like the 16-bit millimetres: depths of at most
    25 cm, silently. Refused, naming the file and the 16-bit depth expected."""
    view = _room(shared_data, tmp_path)
    d = cv2.imread(str(view / "depth_2.pgm"), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16
    cv2.imwrite(str(view / "depth_2.pgm"), (d // 256).astype(np.uint8))
    ds = open_dataset(view)
    assert ds.depth_image(0).max() > 5.0            # the good frames read as before (metres)
    with pytest.raises(DatasetError, match=r"depth_2.pgm: .*8-bit.*expected .*16-bit"):
        ds.depth_image(1)


def test_a_depth_image_of_another_size_than_the_colour_image_is_refused(shared_data, tmp_path):
    """Depth is looked up at the colour image's pixels: a depth image of another size put every depth at the
    wrong pixel (or raised IndexError). Refused, naming the file and both sizes."""
    view = _room(shared_data, tmp_path)
    d = cv2.imread(str(view / "depth_3.pgm"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(view / "depth_3.pgm"), d[:240, :320])
    ds = open_dataset(view)
    with pytest.raises(DatasetError, match=r"depth_3.pgm: the depth image is 320x240, .*640x480"):
        ds.depth_image(2)


def _kitti(shared_data: Path, tmp_path: Path, files=("calib.txt", "poses.txt")) -> Path:
    """A KITTI view of kitti06_stereo: links to the images (a test may delete links), copies of the text files."""
    src, view = shared_data / "kitti06_stereo", tmp_path / "kitti06"
    for sub in ("image_l", "image_r"):
        (view / sub).mkdir(parents=True)
        for p in sorted((src / sub).glob("*.png")):
            (view / sub / p.name).symlink_to(p)
    for name in files:
        (view / name).write_text((src / name).read_text())
    return view


def test_left_and_right_images_missing_different_frames_are_not_paired_by_position(shared_data, tmp_path):
    """Left frame 10 and right frame 20 missing: as many left as right images, and pairs 10-19 were the left
    image of frame k + 1 with the right of frame k (a wrong disparity for every point). Refused, naming the
    image that has no partner."""
    view = _kitti(shared_data, tmp_path, files=("calib.txt",))
    (view / "image_l" / "000010.png").unlink()
    (view / "image_r" / "000020.png").unlink()
    with pytest.raises(DatasetError, match=r"image_l/000010.png: missing, .*image_r has it .*2 image\(s\) without"):
        open_dataset(view)


def _truncated_jpeg(src: Path, dst: Path) -> None:
    ok, buf = cv2.imencode(".jpg", cv2.imread(str(src), cv2.IMREAD_GRAYSCALE))
    assert ok
    dst.write_bytes(buf.tobytes()[: len(buf) // 2])      # a copy cut short: the bottom half never arrived


def test_a_truncated_jpeg_is_refused_not_read_with_a_grey_bottom_half(shared_data, tmp_path):
    """OpenCV decodes a JPEG cut short with a warning on stderr and grey where the data ended: a frame half
    made up was tracked, replayed and measured. Refused, naming the file, by the dataset, the replay camera
    and the commands that read one image (vbnav lines, obstacles)."""
    from vbnav.control.image_files import read_image
    from vbnav.drivers.camera import CameraError
    from vbnav.drivers.replay_camera import ReplayCamera
    from vbnav.drivers.clock import SimClock

    src = shared_data / "kitti06_stereo"
    view = tmp_path / "seq with spaces é"
    (view / "image_l").mkdir(parents=True)
    (view / "calib.txt").write_text((src / "calib.txt").read_text().splitlines()[0] + "\n")
    for k in range(3):
        img = cv2.imread(str(src / "image_l" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(view / "image_l" / f"{k:06d}.jpg"), img)
    _truncated_jpeg(src / "image_l" / "000001.png", view / "image_l" / "000001.jpg")
    bad = view / "image_l" / "000001.jpg"
    ds = open_dataset(view)
    assert ds.image(0).shape == (370, 1226) and ds.image(2).shape == (370, 1226)   # whole files read as before
    with pytest.raises(DatasetError, match=re.escape(str(bad)) + ": .*cut short"):
        ds.image(1)
    with pytest.raises(ValueError, match=re.escape(f"left image {bad}: ") + ".*cut short"):
        read_image(str(bad), "left image")
    cam = ReplayCamera({"path": str(view / "image_l"), "layout": "folder", "rate_hz": 10.0}, SimClock())
    cam.connect()
    assert cam.read(1.0).image.shape == (370, 1226)
    with pytest.raises(CameraError, match=re.escape(str(bad)) + ": .*cut short"):
        cam.read(1.0)


def test_vo_says_which_frames_have_no_ground_truth_and_rpe_pairs_only_neighbours(shared_data, tmp_path, capsys):
    """A ground-truth file without frame 3: the ATE left it out without a word, and the 'RPE (1 frame)' took
    frames 2 and 4 as one pair (two frames of motion). The output says how many frames with a pose have no
    ground truth, and the RPE is over neighbouring frames only, with the number of pairs."""
    import re as _re

    from vbnav.control.cli import main
    from vbnav.vision.geometry import matrix_from_quat

    view = _room(shared_data, tmp_path)
    gt_lines = (view / "groundtruth.txt").read_text().splitlines()
    (view / "groundtruth.txt").write_text("\r\n".join(x for x in gt_lines if not x.startswith("3.0")) + "\r\n")
    out = tmp_path / "traj.txt"
    assert main(["vo", str(view), "--init", "depth", "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "1 of 5 frames with a pose have no ground truth within 0.02 s (frame 3): left out of ATE and RPE" in text
    m = _re.search(r"RPE \(1 frame, (\d+) pairs\) ([0-9.]+) m", text)
    assert m, text
    rows = np.loadtxt(out)
    stamps, est = rows[:, 0], np.tile(np.eye(4), (len(rows), 1, 1))
    for k, r in enumerate(rows):
        est[k, :3, :3], est[k, :3, 3] = matrix_from_quat(r[4:8]), r[1:4]
    ds = open_dataset(view)
    ok, gt = ds.ground_truth_at(stamps)
    assert list(np.flatnonzero(~ok)) == [3]
    errs = []
    for a, b in ((0, 1), (1, 2)):                   # the neighbouring pairs that both have ground truth
        D = np.linalg.inv(np.linalg.inv(gt[a]) @ gt[b]) @ (np.linalg.inv(est[a]) @ est[b])
        errs.append(np.linalg.norm(D[:3, 3]))
    assert int(m.group(1)) == 2
    assert float(m.group(2)) == pytest.approx(np.sqrt(np.mean(np.square(errs))), abs=1e-4)


@pytest.mark.parametrize("files", [("calib.txt",), ("calib.txt", "poses.txt")])
def test_a_kitti_frame_missing_in_the_middle_is_named(shared_data, tmp_path, files):
    """Frame 10 missing on both sides: without times.txt every later frame took the time (and the poses.txt
    line) of the frame before it, silently; with poses.txt the refusal counted lines but named no file.
    Refused, naming the missing frame's file."""
    view = _kitti(shared_data, tmp_path, files=files)
    for side in ("image_l", "image_r"):
        (view / side / "000010.png").unlink()
    with pytest.raises(DatasetError, match=re.escape(str(view / "image_l" / "000010.png")) + r": missing"):
        open_dataset(view)


@pytest.mark.parametrize("name", ["times.txt", "poses.txt", "calib.txt"])
def test_a_text_file_that_is_not_utf8_is_named(shared_data, tmp_path, name):
    """A times.txt saved in UTF-16 (or with a stray byte) raised UnicodeDecodeError: 'vbnav vo' printed
    "'utf-8' codec can't decode byte 0xff" without the file, and the replay camera let it out as a traceback.
    Refused as a DatasetError naming the file."""
    view = _kitti(shared_data, tmp_path)
    if name == "times.txt":
        (view / name).write_text("".join(f"{k / 10}\n" for k in range(51)))
    (view / name).write_bytes((view / name).read_text().encode("utf-16"))
    with pytest.raises(DatasetError, match=re.escape(str(view / name)) + r": .*UTF-8"):
        open_dataset(view)


def test_the_replay_camera_refuses_a_right_image_of_another_size(tmp_path, rng):
    """The replay camera checked the left image's size only: a right image of another size mid-sequence
    reached the stereo stages (disparity of mismatched rows, or a traceback in OpenCV). Refused, naming it."""
    from vbnav.drivers.camera import CameraError
    from vbnav.drivers.clock import SimClock
    from vbnav.drivers.replay_camera import ReplayCamera

    root = tmp_path / "kitti"
    for side in ("image_l", "image_r"):
        (root / side).mkdir(parents=True)
        for i in range(3):
            size = (12, 16) if (side, i) == ("image_r", 1) else (24, 32)
            cv2.imwrite(str(root / side / f"{i:06d}.png"), rng.integers(0, 255, size, dtype=np.uint8))
    (root / "calib.txt").write_text("P0: 500 0 16 0 0 500 12 0 0 0 1 0\nP1: 500 0 16 -250 0 500 12 0 0 0 1 0\n")
    cam = ReplayCamera({"path": str(root)}, SimClock(), size=(32, 24))
    cam.connect()
    assert cam.read(1.0).right.shape == (24, 32)
    with pytest.raises(CameraError, match=re.escape(str(root / "image_r" / "000001.png")) + r".* 16x12"):
        cam.read(1.0)


def test_a_depth_image_listed_but_missing_is_refused_when_the_dataset_opens(shared_data, tmp_path, capsys):
    """depth.txt listing a file that is not there was found only when tracking reached it: vbnav vo tracked
    the frames before it and then exited without a trajectory. Refused at once, naming the file and the list."""
    from vbnav.control.cli import main

    view = _room(shared_data, tmp_path)
    (view / "depth_4.pgm").unlink()
    with pytest.raises(DatasetError, match=re.escape(str(view / "depth_4.pgm")) + r": listed in .*depth.txt.* missing"):
        open_dataset(view)
    assert main(["vo", str(view), "--out", str(tmp_path / "t.txt"), "--quiet"]) == 2
    cap = capsys.readouterr()
    assert "depth_4.pgm: listed in" in cap.err and "pose for" not in cap.out


def test_two_ground_truth_poses_at_one_time_are_refused(shared_data, tmp_path):
    """groundtruth.txt with two different poses at one time (two exports concatenated): the lookup took
    whichever the sort put nearest, silently. Refused, naming the file and both entries; a line repeated with
    the same pose, and lines out of order (which are sorted), are read as before."""
    view = _room(shared_data, tmp_path)
    gt = view / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    before = open_dataset(view).gt_poses
    gt.write_text("\n".join([lines[0], lines[3], lines[1], lines[2], lines[2]] + lines[4:]) + "\n")
    np.testing.assert_allclose(open_dataset(view).gt_poses, before)
    moved = lines[2].split()
    moved[1] = str(float(moved[1]) + 0.5)
    gt.write_text("\n".join(lines + [" ".join(moved)]) + "\n")
    with pytest.raises(DatasetError, match=re.escape(str(gt)) + r": lines 3 and 7 .*1 s.*different poses"):
        open_dataset(view)


def test_vo_says_which_frames_have_no_depth_image(shared_data, tmp_path, capsys):
    """A depth.txt whose entry for frame 2 is 0.5 s off: frame 2 got no depth (nearest within 20 ms) and was
    tracked without it, without a word. vbnav vo says which frames have no depth image and how it took them."""
    from vbnav.control.cli import main

    view = _room(shared_data, tmp_path)
    dl = (view / "depth.txt").read_text().replace("2.000000 depth_3.pgm", "2.500000 depth_3.pgm")
    (view / "depth.txt").write_text(dl)
    ds = open_dataset(view)
    assert [d is None for d in ds.depth] == [False, False, True, False, False]
    assert main(["vo", str(view), "--init", "depth", "--out", str(tmp_path / "t.txt"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert ("1 of 5 frames have no depth image within 0.02 s in " + str(view / "depth.txt") + " (frame 2): "
            "tracked without depth") in out


@pytest.mark.parametrize("command", ["obstacles", "lines"])
def test_a_pair_of_an_8_bit_and_a_16_bit_image_is_refused(shared_data, tmp_path, capsys, command):
    """An 8-bit left image with a 16-bit right one (one side re-exported): both were put on the pair's common
    16-bit range, the left image came out black, and vbnav obstacles reported an obstacle at 4 m (exit 0) where
    there is a road; vbnav lines reconstructed a third of the segments. Refused (exit 2), naming both files and
    their bit depths."""
    from vbnav.control.cli import main

    if command == "obstacles":
        src = shared_data / "kitti06_stereo"
        left, right, calib = src / "image_l" / "000025.png", src / "image_r" / "000025.png", src / "calib.txt"
        extra = ["--camera-height", "1.65"]
    else:
        src = shared_data / "indoor_stereo" / "euroc_v101"
        left = sorted((src / "cam0").glob("*.png"))[0]
        right, calib = src / "cam1" / left.name, src / "stereo_rectify.yaml"
        extra = ["--out", str(tmp_path / "lines.json")]
    right16 = tmp_path / "right16.png"
    cv2.imwrite(str(right16), cv2.imread(str(right), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 256)
    code = main([command, "--left", str(left), "--right", str(right16), "--calib", str(calib)] + extra)
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"left {left} is uint8 but right {right16} is uint16" in err


def test_calibrate_stereo_refuses_pairs_whose_numbers_do_not_match(shared_data, tmp_path, capsys):
    """left03 and right07 missing from OpenCV's stereo samples: 12 images on each side, paired by sorted
    position, so left04 was calibrated with right03 and so on (a wrong extrinsic, written without a word).
    Refused, naming the image without a partner."""
    from vbnav.control.cli import main

    src = shared_data / "calib_chessboard" / "stereo"
    for side, gone in (("left", "left03.jpg"), ("right", "right07.jpg")):
        (tmp_path / side).mkdir()
        for f in sorted(src.glob(f"{side}*.jpg")):
            if f.name != gone:
                (tmp_path / side / f.name).symlink_to(f)
    code = main(["calibrate", "stereo", str(tmp_path / "left"), str(tmp_path / "right"), "--square", "1",
                 "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"{tmp_path / 'right' / 'right03.jpg'}: no left image numbered 03 in {tmp_path / 'left'}" in err
    assert not (tmp_path / "out").exists()


def test_a_time_that_does_not_increase_is_named_by_its_line(shared_data, tmp_path):
    """times.txt with a comment header, blank lines and CRLF endings is read as before; a time repeated on line
    7 was reported as 'entry 4', which is not the line an editor shows. The refusal names the lines."""
    view = _kitti(shared_data, tmp_path)
    times = [f"{k / 10:.1f}" for k in range(51)]
    (view / "times.txt").write_bytes(("# t [s]\r\n\r\n" + "\r\n\r\n".join(times[:2]) + "\r\n" + "\r\n".join(times[2:])
                                      + "\r\n").encode())
    np.testing.assert_allclose(open_dataset(view).stamps, np.arange(51) / 10)
    times[3] = times[2]
    text = "# t [s]\n\n" + "\n\n".join(times[:2]) + "\n" + "\n".join(times[2:]) + "\n"
    (view / "times.txt").write_text(text)
    assert text.splitlines()[6 - 1] == "0.2" and text.splitlines()[7 - 1] == "0.2"
    with pytest.raises(DatasetError, match=re.escape(str(view / "times.txt")) + r":7: 0.2 s is not after line 6's "
                                                                                  r"0.2 s: expected increasing times"):
        open_dataset(view)


def test_calibrate_refuses_a_truncated_jpeg_view(shared_data, tmp_path, capsys):
    """A board view cut short (80 % of left01.jpg) was decoded with a grey bottom, its corners found in the part
    that arrived, and calibrated from without a word. Refused like every other reader, naming the file."""
    from vbnav.control.cli import main

    src = shared_data / "calib_chessboard" / "stereo"
    (tmp_path / "left").mkdir()
    for f in sorted(src.glob("left*.jpg")):
        (tmp_path / "left" / f.name).symlink_to(f)
    bad = tmp_path / "left" / "left01.jpg"
    bad.unlink()
    bad.write_bytes((src / "left01.jpg").read_bytes()[: int(0.8 * (src / "left01.jpg").stat().st_size)])
    code = main(["calibrate", "intrinsics", "--images", str(tmp_path / "left"), "--square", "1",
                 "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"{bad}: the JPEG is cut short" in err
    assert not (tmp_path / "out").exists()


def test_vo_writes_the_trajectory_so_far_when_an_image_mid_run_cannot_be_read(shared_data, tmp_path, capsys):
    """Frame 3's colour image unreadable: vo ended with the error and no trajectory, the minutes of tracking
    before it lost. The poses of the frames before it are written (and the status file), the error names the
    file, and the exit is non-zero."""
    from vbnav.control.cli import main

    view = _room(shared_data, tmp_path)
    bad = view / "color_4.png"
    bad.unlink()
    bad.write_bytes(b"not an image")
    out, status = tmp_path / "traj.txt", tmp_path / "status.txt"
    assert main(["vo", str(view), "--init", "depth", "--out", str(out), "--status-out", str(status),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert re.search(re.escape(str(bad)) + r": missing or not a readable image", err), err
    assert f"3 frame(s) with a pose (frames 0-2) written to {out}" in err, err
    rows = np.loadtxt(out)
    assert list(rows[:, 0]) == [0.0, 1.0, 2.0]             # the frames tracked before it
    states = [line.split()[1] for line in status.read_text().splitlines()[1:]]
    assert states[:3] == ["init", "tracked", "tracked"] and states[3:] == ["lost", "lost"]
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == ["status.txt", "traj.txt"]  # no temp left


def test_left_and_right_image_folders_swapped_are_refused(shared_data, tmp_path):
    """image_l/ holding the right camera's images and image_r/ the left's (a copy mislabelled): every disparity
    had the wrong sign, stereo depth behind the camera, and the dataset opened without a word. The first pair
    is checked: most matched features must lie further right in the left image; refused naming both folders."""
    src, view = shared_data / "kitti06_stereo", tmp_path / "swapped"
    for sub, other in (("image_l", "image_r"), ("image_r", "image_l")):
        (view / sub).mkdir(parents=True)
        for p in sorted((src / other).glob("*.png"))[:3]:
            (view / sub / p.name).symlink_to(p)
    (view / "calib.txt").write_text((src / "calib.txt").read_text())
    with pytest.raises(DatasetError, match=re.escape(f"{view / 'image_l'} and {view / 'image_r'}") +
                       r": .*swapped"):
        open_dataset(view)
    (view / "image_l").rename(view / "tmp")
    (view / "image_r").rename(view / "image_l")
    (view / "tmp").rename(view / "image_r")
    assert len(open_dataset(view)) == 3                     # the right way round opens as before
