"""Replacing a route never loses the old one before the new one is complete."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from vbnav.control import route as route_mod
from vbnav.control.route import RouteError, RouteWriter, load_route, stray_route_dirs

from test_route import CAM, MOUNT, make_kf, write_route


class Killed(Exception):
    pass


@pytest.mark.parametrize("k", [0, 1, 4])
def test_interrupted_overwrite_keeps_the_old_route(tmp_path, rng, k):
    old = write_route(tmp_path / "r", rng, n=3)
    with pytest.raises(Killed):
        with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True) as w:
            for i in range(k):
                w.append(make_kf(rng, i))
            raise Killed
    r = load_route(tmp_path / "r")
    assert r.complete and len(r) == 3 and r.keyframes[2].distance == old[2].distance
    left = stray_route_dirs(tmp_path / "r")
    assert [p.name for p in left] == [f".r.partial-{os.getpid()}"]
    assert len(load_route(left[0])) == k and not load_route(left[0]).complete   # what was taught is kept


def test_abandoned_writer_keeps_the_old_route(tmp_path, rng):
    write_route(tmp_path / "r", rng, n=3)
    w = RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True)
    w.append(make_kf(rng, 0))                    # the process dies here: close() never runs
    assert len(load_route(tmp_path / "r")) == 3


@pytest.mark.parametrize("exchange", [True, False])
def test_completed_overwrite_swaps_in_and_leaves_nothing(tmp_path, rng, monkeypatch, exchange):
    if not exchange:
        monkeypatch.setattr(route_mod, "_exchange", lambda a, b: False)
    write_route(tmp_path / "r", rng, n=3)
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True) as w:
        for i in range(5):
            w.append(make_kf(rng, i))
        assert len(load_route(tmp_path / "r")) == 3          # the old one until the end
    r = load_route(tmp_path / "r")
    assert r.complete and len(r) == 5 and stray_route_dirs(tmp_path / "r") == []
    assert sorted(os.listdir(tmp_path)) == ["r"]


def test_crash_between_the_renames_is_pointed_at(tmp_path, rng, monkeypatch):
    write_route(tmp_path / "r", rng, n=3)
    monkeypatch.setattr(route_mod, "_exchange", lambda a, b: False)
    real_rename, calls = os.rename, []

    def rename(a, b):
        calls.append(a)
        if len(calls) == 2:
            raise Killed
        real_rename(a, b)
    monkeypatch.setattr(route_mod.os, "rename", rename)
    w = RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True)
    w.append(make_kf(rng, 0))
    with pytest.raises(Killed):
        w.close()
    monkeypatch.undo()
    with pytest.raises(RouteError, match=r"interrupted replacement left \.r\.old-\d+, \.r\.partial-\d+"):
        load_route(tmp_path / "r")
    old, new = stray_route_dirs(tmp_path / "r")
    assert len(load_route(old)) == 3 and load_route(old).complete and len(load_route(new)) == 1


def test_overwrite_refuses_a_directory_that_is_not_a_route(tmp_path, rng):
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "thesis.tex").write_text("years of work")
    with pytest.raises(RouteError, match="'thesis.tex', which is not a route file"):
        RouteWriter(tmp_path / "home", "sim", CAM, MOUNT, overwrite=True)
    assert os.listdir(tmp_path / "home") == ["thesis.tex"] and stray_route_dirs(tmp_path / "home") == []


@pytest.mark.parametrize("kill_after_s", [1.0, 3.0, 5.0])
def test_killed_teach_overwrite_keeps_the_old_route(tmp_path, rng, kill_after_s):
    write_route(tmp_path / "r", rng, n=3)
    proc = subprocess.Popen([sys.executable, "-m", "vbnav.control.cli", "teach", "--out", str(tmp_path / "r"),
                             "--overwrite"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(kill_after_s)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    r = load_route(tmp_path / "r")
    assert r.complete and len(r) == 3 and r.camera == CAM
    assert all(p.name.startswith(".r.partial-") for p in stray_route_dirs(tmp_path / "r"))


def test_teach_overwrite_completes_the_swap(tmp_path, rng):
    write_route(tmp_path / "r", rng, n=3)
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "teach", "--out", str(tmp_path / "r"),
                        "--duration", "3"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "use --overwrite" in r.stdout + r.stderr
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "teach", "--out", str(tmp_path / "r"),
                        "--overwrite", "--duration", "3"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    new = load_route(tmp_path / "r")
    assert new.complete and new.camera.width == 640 and stray_route_dirs(tmp_path / "r") == []


def test_killed_demo_keeps_the_route_of_the_last_demo(tmp_path, rng):
    write_route(tmp_path / "out" / "route", rng, n=3)
    proc = subprocess.Popen([sys.executable, "-m", "vbnav.control.cli", "demo", "--out", str(tmp_path / "out")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(4.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    r = load_route(tmp_path / "out" / "route")
    assert r.complete and len(r) == 3 and r.camera == CAM


def test_teach_overwrite_that_fails_keeps_the_old_route(tmp_path, rng):
    """A teach that ends in a fault (here the drive's bus is lost 2 s in) is not a complete route: it must
    not take the old route's place, and says where the keyframes it did record are."""
    write_route(tmp_path / "r", rng, n=3)
    cfg = tmp_path / "lossy.yaml"
    cfg.write_text("drive:\n  driver: sim\n  reconnect_window_s: 0.2\n  options: {fail_after_s: 2.0}\n"
                   "controller:\n  teach: room_loop\n")
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "teach", "-c", str(cfg), "--out",
                        str(tmp_path / "r"), "--overwrite", "--duration", "6"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 3, r.stdout + r.stderr
    old = load_route(tmp_path / "r")
    assert old.complete and len(old) == 3 and old.camera == CAM
    left = stray_route_dirs(tmp_path / "r")
    assert len(left) == 1 and left[0].name.startswith(".r.partial-")
    partial = load_route(left[0])
    assert not partial.complete and len(partial) >= 1
    assert f"the route at {tmp_path / 'r'} is unchanged" in r.stdout and str(left[0]) in r.stdout, r.stdout
    # teaching into a new folder: the keyframes stay, marked incomplete, and the exit code says it failed
    r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "teach", "-c", str(cfg), "--out",
                        str(tmp_path / "new"), "--duration", "6"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 3 and "marked incomplete" in r.stdout, r.stdout + r.stderr
    assert not load_route(tmp_path / "new").complete


def test_overwrite_replaces_a_route_with_the_temporary_files_of_an_interrupted_write(tmp_path, rng):
    """A teach killed in the middle of writing a keyframe leaves ``.kf_00003.npz.<random>.tmp`` (the atomic
    writer's name; loading ignores it). --overwrite refused that route as 'not a route file'."""
    write_route(tmp_path / "r", rng, n=3)
    (tmp_path / "r" / ".kf_00003.npz.k2j_3h4x.tmp").write_bytes(b"PK\x03\x04")
    (tmp_path / "r" / ".manifest.json.a8b9c0d1.tmp").write_text('{"format": "vbn')
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True) as w:
        for i in range(2):
            w.append(make_kf(rng, i))
    assert len(load_route(tmp_path / "r")) == 2 and not any(p.name.endswith(".tmp")
                                                            for p in (tmp_path / "r").iterdir())
    (tmp_path / "r" / ".notes.txt.a8b9c0d1.tmp").write_text("not ours")
    with pytest.raises(RouteError, match="holds '.notes.txt.a8b9c0d1.tmp', which is not a route file"):
        RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True)


def test_a_partial_route_left_by_an_earlier_process_with_our_pid_is_kept(tmp_path, rng):
    """After a reboot a service often gets the pid it had before: a replacement interrupted then left
    ``.r.partial-<pid>`` (recorded keyframes, which nothing is to delete), and the next replacement by a
    process with that pid deleted it before writing its own."""
    write_route(tmp_path / "r", rng, n=3)
    earlier = tmp_path / f".r.partial-{os.getpid()}"
    write_route(earlier, rng, n=2)
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True) as w:
        assert w.directory != earlier
        for i in range(4):
            w.append(make_kf(rng, i))
    assert len(load_route(tmp_path / "r")) == 4 and len(load_route(earlier)) == 2
    assert stray_route_dirs(tmp_path / "r") == [earlier]


@pytest.mark.parametrize("exchange", [True, False])
def test_an_old_route_left_by_an_earlier_process_with_our_pid_is_kept(tmp_path, rng, monkeypatch, exchange):
    """``.r.old-<pid>`` (the complete old route of a swap a crash cut between its renames) from an earlier
    process that had our pid: the swap renamed onto it, failed (directory not empty) and the teach ended with
    an OSError, the new route in place (exchange) or not swapped in at all."""
    if not exchange:
        monkeypatch.setattr(route_mod, "_exchange", lambda a, b: False)
    write_route(tmp_path / "r", rng, n=3)
    earlier = tmp_path / f".r.old-{os.getpid()}"
    write_route(earlier, rng, n=2)
    with RouteWriter(tmp_path / "r", "sim", CAM, MOUNT, overwrite=True) as w:
        for i in range(4):
            w.append(make_kf(rng, i))
    assert len(load_route(tmp_path / "r")) == 4 and len(load_route(earlier)) == 2
    assert stray_route_dirs(tmp_path / "r") == [earlier]


def test_an_installed_route_directory_is_durable(tmp_path, rng, disk_log):
    """A pulled or pushed route is a staging folder renamed into place: its own entries (the files written
    into it) and the rename must reach the disk, or a power cut leaves an empty or missing route."""
    staging = tmp_path / "staging"
    write_route(staging, rng)
    disk_log.clear()        # what the install does (route_transfer writes the staging files with plain writes)
    route_mod.install_route_dir(staging, tmp_path / "r", overwrite=False)
    assert ("fsync folder", str(staging)) in disk_log
    assert disk_log.durable(tmp_path / "r"), disk_log
    assert load_route(tmp_path / "r").keyframes
