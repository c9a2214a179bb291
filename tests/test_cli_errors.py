"""Every ``vbnav`` command on bad input, as a process: exit 2, one line on stderr naming the file, field,
argument or device, and never a traceback (issue 12, point 9).

A missing device is the one exception: the documented exit code for it is 3 (hardware/device error),
with the cause named in the run's summary. The cases run concurrently, each in its own process forked from
one interpreter that has imported the command line (tests/cli_forks.py), then each is asserted on its own.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]
# The module fixture runs all ~150 cases before the first test: on two busy cores that can take longer than
# the suite's 300 s per test. Each case keeps its own 120 s limit.
pytestmark = pytest.mark.timeout(1200)

W, H = 64, 48     # the tiny test sequence's images
K_ROW = f"50 0 {W / 2} 0 0 50 {H / 2} 0 0 0 1 0"          # P0 of the tiny sequence
P1_ROW = f"50 0 {W / 2} -5 0 50 {H / 2} 0 0 0 1 0"        # baseline 0.1 m
STEREO = f"width: {W}\nheight: {H}\nfx: 50\nfy: 50\ncx: {W / 2}\ncy: {H / 2}\nbaseline: 0.1\n"
CAMERA = f"width: {W}\nheight: {H}\nfx: 50\nfy: 50\ncx: {W / 2}\ncy: {H / 2}\n"

# Configurations that a case also names as its output (each its own: the cases run concurrently).
SELF_CONFIGS = ("self_map.yaml", "self_goto.yaml", "self_run.yaml")
SELF_CONFIG = "sim: {seed: 3}\ncamera: {options: {stereo_baseline: 0.075}}\ntelemetry: {enabled: false}\n"

OVERWRITE = "--overwrite replaces an existing --record file; without --record it has nothing to replace"

# id, arguments ({d}: the fixture folder), expected exit code, text the error must contain
CASES = [
    # top level
    ("unknown-command", "fly", 2, "fly"),
    # calibrate
    ("calibrate-live-camera-missing", "calibrate intrinsics --live -c {d}/v4l2.yaml --out {d}/calib", 3,
     "camera /dev/video99 not found"),
    ("calibrate-mount-camera-missing", "calibrate mount --live -c {d}/v4l2.yaml --dry-run", 3,
     "camera /dev/video99 not found"),
    ("calibrate-board-thickness-nan", "calibrate mount --image {d}/left.png --board-thickness nan --dry-run", 2,
     "--board-thickness"),
    ("calibrate-board-thickness-negative", "calibrate mount --image {d}/left.png --board-thickness -0.01 --dry-run",
     2, "--board-thickness"),
    ("calibrate-dictionary-not-one", "calibrate intrinsics --images {d}/empty --board charuco --marker 0.01 "
     "--dictionary CharucoBoard --out {d}/calib", 2, "--dictionary: unknown ArUco dictionary 'CharucoBoard'"),
    ("calibrate-dictionary-chessboard", "calibrate mount --image {d}/left.png --dictionary DICT_BOGUS --dry-run", 2,
     "--dictionary: unknown ArUco dictionary 'DICT_BOGUS'"),
    ("calibrate-min-sharpness-nan", "calibrate intrinsics --images {d}/empty --min-sharpness nan --out {d}/calib", 2,
     "--min-sharpness"),
    # config
    ("config-missing", "config check -c {d}/nope.yaml", 2, "nope.yaml"),
    ("config-dir", "config check -c {d}/empty", 2, "empty"),
    ("config-garbage-yaml", "config check -c {d}/garbage.yaml", 2, "garbage.yaml"),
    ("config-unknown-key", "config show -c {d}/unknown.yaml", 2, "robot.bogus"),
    ("config-bad-number", "config check -c {d}/badnum.yaml", 2, "robot.wheel_radius"),
    ("config-nan-focal", "config check -c {d}/cfg_nanfx.yaml", 2, "camera.fx"),
    ("config-inf-focal", "config check -c {d}/cfg_inffx.yaml", 2, "camera.fx"),
    ("config-cx-outside", "config check -c {d}/cfg_cx.yaml", 2, "cx"),
    ("config-bad-action", "config frob", 2, "frob"),
    ("config-reference-config", "config reference -c {d}/nope.yaml", 2, "--config goes with check and show"),
    # demo
    ("demo-out-file", "demo --out {d}/afile.txt", 2, "afile.txt"),
    ("demo-seed", "demo --seed x", 2, "--seed"),
    ("demo-repeats", "demo --repeats 0 --out {d}/demo_out", 2, "--repeats"),
    # a negative seed was a traceback from numpy ('this is a bug in vbnav'); sim.seed -1 was valid
    ("demo-seed-negative", "demo --seed -1 --out {d}/demo_out", 2, "argument --seed: expected an integer >= 0"),
    ("config-seed-negative", "config check -c {d}/cfg_seed.yaml", 2, "sim.seed"),
    ("run-seed-negative", "run -c {d}/cfg_seed.yaml --duration 0.1", 2, "sim.seed"),
    ("demo-garbage-config", "demo -c {d}/garbage.yaml", 2, "garbage.yaml"),
    ("demo-hardware-config", "demo -c {d}/dxl.yaml", 2, "dxl.yaml"),
    ("demo-record-dir", "demo --out {d}/demo_out --record {d}/empty", 2, "--record"),
    ("demo-overwrite-no-record", "demo --out {d}/demo_out --overwrite", 2, OVERWRITE),
    # emulate
    ("emulate-no-device", "emulate", 2, "DEVICE"),
    ("emulate-ids", "emulate dynamixel --ids 1,1", 2, "--ids"),
    ("emulate-model", "emulate dynamixel --model XX-1", 2, "XX-1"),
    ("emulate-link-no-folder", "emulate dynamixel --link {d}/nope/ttyX", 2, "nope"),
    ("emulate-link-file", "emulate odrive --link {d}/afile.txt", 2, "afile.txt"),
    ("emulate-watchdog", "emulate odrive --watchdog-s nan", 2, "--watchdog-s"),
    # goto
    ("goto-goal-nan", "goto --goal 1 nan 0", 2, "--goal"),
    ("goto-goal-word", "goto --goal 1 x 0", 2, "--goal"),
    ("goto-duration", "goto --goal 1 1 0 --duration -1", 2, "--duration"),
    ("goto-config-missing", "goto --goal 1 1 0 -c {d}/nope.yaml", 2, "nope.yaml"),
    # lines: --min-epipolar-angle 180 let horizontal segments through (its sine is 0), 95 acted as 85
    ("lines-epipolar-angle", "lines --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml --out "
     "{d}/seg.json --min-epipolar-angle 180", 2, "argument --min-epipolar-angle: expected an angle to the rows"),
    # lines: one image as both (given twice, or two copies) reconstructed segments kilometres away, score 1.0
    ("lines-same-file", "lines --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml --out {d}/seg.json",
     2, "--left and --right are the same file"),
    ("lines-same-image", "lines --left {d}/left.png --right {d}/left_copy.png --calib {d}/stereo.yaml --out "
     "{d}/seg.json", 2, "are the same image"),
    # lines: a nearest depth beyond what the rig resolves left no disparity to search: a cv2 traceback
    ("lines-min-depth-beyond-the-rig", "lines --left {d}/left.png --right {d}/right.png --calib {d}/stereo.yaml "
     "--out {d}/seg.json --min-depth 100", 2, "--min-depth 100 m: the largest disparity searched, fx B / depth"),
    # a folder given as an image or a calibration was "file not found"; a device as a map "map file not found"
    ("lines-left-dir", "lines --left {d}/empty --right {d}/right.png --calib {d}/stereo.yaml --out {d}/seg.json", 2,
     "empty: is a directory, expected an image file"),
    ("lines-calib-dir", "lines --left {d}/left.png --right {d}/right.png --calib {d}/empty --out {d}/seg.json", 2,
     "empty: is a directory, expected a calibration file"),
    ("map-info-device", "map info /dev/null", 2, "/dev/null: is not a regular file, expected a map file"),
    # Middlebury's own calib.txt said "line 1: expected numbers, got 'cam0=[...'"
    ("lines-middlebury-calib", "lines --left {d}/left.png --right {d}/right.png --calib {d}/middlebury_calib.txt "
     "--out {d}/seg.json", 2, "a Middlebury calib.txt (cam0=[...], doffs, baseline in mm), which vbnav does not read"),
    # --min-depth nearer than half the image's disparity reaches was cut to it without a word (fB 5 px m, 32 px)
    ("lines-min-depth-nearer-than-the-search", "lines --left {d}/left.png --right {d}/right.png --calib "
     "{d}/stereo.yaml --out {d}/seg.json --min-depth 0.1", 2, "is more than half the image width (32 px)"),
    # PNG bytes were written under a .jpg name
    ("lines-overlay-jpg", "lines --left {d}/left.png --right {d}/right.png --calib {d}/stereo.yaml --out "
     "{d}/seg.json --overlay-out {d}/o.jpg", 2, "o.jpg: expected a file name ending in .png"),
    # a --min-depth nearer than 256 disparities reach was cut to them without a word
    ("obstacles-min-depth-beyond-sgbm", "obstacles --left {d}/left.png --right {d}/right.png --calib "
     "{d}/stereo.yaml --min-depth 0.01", 2, "SGBM searches at most 256: the nearest depth it can cover is 0.0195 m"),
    ("obstacles-overlay-jpg", "obstacles --left {d}/left.png --right {d}/right.png --calib {d}/stereo.yaml "
     "--overlay-out {d}/o.jpg", 2, "expected a file name ending in .png"),
    ("map-plot-jpg", "map plot {d}/afile.txt --out {d}/p.jpg", 2, "expected a file name ending in .png"),
    # monitor
    ("monitor-timeout", "monitor --once --timeout -1", 2, "--timeout"),
    ("monitor-refresh", "monitor --refresh 0", 2, "--refresh"),
    ("monitor-endpoint", "monitor --once --connect garbage", 2, "garbage"),
    ("monitor-json-live", "monitor --json", 2, "--json prints one state with --once"),
    ("monitor-all-robot", "monitor --all --robot r1", 2, "--robot names one robot"),
    ("monitor-all-config", "monitor --all -c sim", 2, "--config names one robot"),
    ("monitor-refresh-once", "monitor --once --refresh 2", 2, "--refresh is the live view's rate"),
    # --count -3 waited for no robot (exit 0), --count 0 without --all was not refused: both tried to connect
    ("monitor-count-negative", "monitor --all --once --count -3", 2,
     "argument --count: expected a number of robots >= 1, got '-3'"),
    ("monitor-count-zero", "monitor --count 0", 2, "argument --count: expected a number of robots >= 1, got '0'"),
    # obstacles
    ("obstacles-1x1-kitti-calib", "obstacles --left {d}/one.png --right {d}/one.png --calib {d}/good/calib.txt",
     2, "calib.txt: P0 cx"),
    ("obstacles-1x1-yaml-calib", "obstacles --left {d}/one.png --right {d}/one_b.png --calib {d}/stereo_1x1.yaml",
     2, "one.png: the pair is 1x1, too narrow"),   # two images: one twice is refused as such first
    ("obstacles-sizes", "obstacles --left {d}/left.png --right {d}/right_big.png --calib {d}/stereo.yaml",
     2, "right_big.png"),
    ("obstacles-calib-missing", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/nope.txt",
     2, "nope.txt"),
    ("obstacles-calib-dir", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/empty", 2, "empty"),
    ("obstacles-calib-garbage", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/garbage.yaml",
     2, "garbage.yaml"),
    ("obstacles-calib-nan-focal", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo_nan.yaml",
     2, "fx"),
    ("obstacles-calib-zero-baseline",
     "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo_base0.yaml", 2, "baseline"),
    ("obstacles-calib-cx-outside", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo_cx.yaml",
     2, "cx"),
    ("obstacles-kitti-p1-is-p0", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/zerobase/calib.txt",
     2, "P1"),
    ("obstacles-calib-mono", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/camera_info.yaml",
     2, "camera_info.yaml: a single-camera calibration"),
    ("obstacles-calib-two-fields", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo_2bad.yaml",
     2, "stereo_2bad.yaml: fx: Input should be a valid number, unable to parse string as a number; baseline: "),
    ("obstacles-left-missing", "obstacles --left {d}/nope.png --right {d}/left.png --calib {d}/stereo.yaml",
     2, "nope.png"),
    ("obstacles-left-dir", "obstacles --left {d}/empty --right {d}/left.png --calib {d}/stereo.yaml", 2, "empty"),
    ("obstacles-left-not-image", "obstacles --left {d}/afile.txt --right {d}/left.png --calib {d}/stereo.yaml",
     2, "afile.txt"),
    ("obstacles-block-size", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--block-size 4", 2, "--block-size"),
    ("obstacles-bad-number", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--obstacle-height nan", 2, "--obstacle-height"),
    ("obstacles-mask-out-dir", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--mask-out {d}/empty", 2, "--mask-out"),
    ("obstacles-no-input", "obstacles --calib {d}/stereo.yaml", 2, "--left"),
    # --pitch-deg 400 ran as 40 (the stereo YAML's mount allows -90..90, roll -45..45)
    ("obstacles-pitch-range", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--camera-height 0.3 --pitch-deg 400", 2, "argument --pitch-deg: expected degrees in -90..90, got '400'"),
    ("obstacles-roll-range", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--camera-height 0.3 --roll-deg -60", 2, "argument --roll-deg: expected degrees in -45..45, got '-60'"),
    ("obstacles-disparity-missing", "obstacles --disparity {d}/nope.npy --calib {d}/stereo.yaml", 2, "nope.npy"),
    # record-info
    ("record-info-dir", "record-info {d}/empty", 2, "empty"),
    ("record-info-missing", "record-info {d}/nope.mcap", 2, "nope.mcap"),
    ("record-info-not-mcap", "record-info {d}/afile.txt", 2, "afile.txt"),
    # repeat
    ("repeat-missing", "repeat --path {d}/nope", 2, "nope"),
    ("repeat-file", "repeat --path {d}/afile.txt", 2, "afile.txt"),
    ("repeat-empty-dir", "repeat --path {d}/empty", 2, "manifest.json"),
    ("repeat-duration", "repeat --path {d}/empty --duration nan", 2, "--duration"),
    ("repeat-garbage-config", "repeat --path {d}/empty -c {d}/garbage.yaml", 2, "garbage.yaml"),
    ("repeat-record-dir", "repeat --path {d}/empty --record {d}/empty", 2, "--record"),
    ("repeat-overwrite-no-record", "repeat --path {d}/empty --overwrite", 2, OVERWRITE),
    # two outputs naming one file, or an output naming an input: one overwrote the other
    ("vo-out-status-same", "vo {d}/good --out {d}/same.txt --status-out {d}/same.txt --quiet", 2,
     "--out and --status-out name the same file"),
    ("lines-overlay-is-left", "lines --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml --out "
     "{d}/seg.json --overlay-out {d}/left.png", 2,
     "left.png: is the --left file; writing it would replace the input"),
    ("obstacles-mask-overlay-same", "obstacles --left {d}/left.png --right {d}/left.png --calib {d}/stereo.yaml "
     "--mask-out {d}/same.png --overlay-out {d}/same.png", 2, "--mask-out and --overlay-out name the same file"),
    ("map-plot-out-is-map", "map plot {d}/afile.txt --out {d}/afile.txt", 2, "afile.txt: is the MAP file"),
    # route: a file given as a route (or folder of routes) was 'route directory does not exist' / 'no such directory'
    ("route-check-file", "route check {d}/afile.txt", 2, "afile.txt: is a file, expected a route directory"),
    ("route-list-file", "route list {d}/afile.txt", 2, "afile.txt: is a file, expected a folder of routes"),
    # route pull / push: options they would not use
    ("route-pull-to-and-config", "route pull r1 loop --to {d}/empty -c sim", 2, "a pull reads nothing from it"),
    ("route-push-robot", "route push r1 {d}/empty --robot r2", 2, "--robot r2: route push names the robot"),
    # -c gives a push its secret only: a configuration without one was read for nothing, the push unsigned
    ("route-push-config-no-secret", "route push r1 {d}/empty -c sim", 2,
     "sets no telemetry.shared_secret_file, the one thing a push reads from it"),
    ("route-push-config-and-secret-file", "route push r1 {d}/empty -c sim --secret-file {d}/afile.txt", 2,
     "with --secret-file"),
    # run
    ("run-config-missing", "run -c {d}/nope.yaml", 2, "nope.yaml"),
    ("run-config-dir", "run -c {d}/empty", 2, "empty"),
    ("run-unknown-key", "run -c {d}/unknown.yaml", 2, "robot.bogus"),
    ("run-duration-negative", "run --duration -1", 2, "--duration"),
    ("run-duration-nan", "run --duration nan", 2, "--duration"),
    ("run-controller", "run --controller fly", 2, "--controller"),
    ("run-record-dir", "run --no-camera --duration 0.1 --record {d}/empty", 2, "--record"),
    ("run-record-no-folder", "run --no-camera --duration 0.1 --record {d}/nope/x.mcap", 2, "nope"),
    ("run-overwrite-no-record", "run --no-camera --duration 0.1 --overwrite", 2, OVERWRITE),
    # a map, a grown map or a calibration already recorded was replaced without asking (teach --out refuses)
    ("map-build-out-exists", "map build --out {d}/afile.txt", 2, "a map is already there"),
    ("goto-map-out-exists", "goto --map {d}/afile.txt --map-out {d}/unknown.yaml --goal 0 1 0", 2,
     "a map is already there"),
    ("goto-overwrite-no-map-out", "goto --goal 0 1 0 --overwrite", 2, "without --map-out or --record it has nothing"),
    # map build drove the (default) script whatever controller.kind said; a --duration beyond the script was cut
    ("map-build-idle-controller", "map build -c {d}/v4l2.yaml --out {d}/map.json", 2,
     "controller.kind is 'idle'; map build drives controller.script"),
    ("map-build-duration-beyond-script", "map build --out {d}/map.json --duration 30", 2,
     "sim_stereo.yaml: controller.script ends after 8 s, and the run with it"),
    ("run-duration-beyond-script", "run --no-camera --duration 30", 2, "controller.script ends after 8 s"),
    # --realtime with a real drive passed when the config's kept sim section said realtime: true
    ("run-realtime-real-drive", "run -c {d}/dxl_realtime.yaml --realtime --no-camera --duration 0.2", 2,
     "dxl_realtime.yaml: drive.driver dynamixel and camera.driver v4l2 run on the wall clock anyway"),
    # teleop on the simulated clock: the network is not opened, the robot stood still until the end
    ("run-teleop-simulated-clock", "run --controller teleop --no-camera --duration 1", 2,
     "--controller teleop on the simulated clock (faster than real time): the network is not opened"),
    # an output named as the run's own configuration replaced it with a map or a recording (exit 0)
    ("map-build-out-is-config", "map build -c {d}/self_map.yaml --out {d}/self_map.yaml --overwrite", 2,
     "self_map.yaml: is the --config file"),
    ("goto-map-out-is-config", "goto -c {d}/self_goto.yaml --map {d}/afile.txt --map-out {d}/self_goto.yaml "
     "--overwrite --goal 0 1 0", 2, "self_goto.yaml: is the --config file"),
    ("run-record-is-config", "run -c {d}/self_run.yaml --no-camera --duration 0.1 --record {d}/self_run.yaml "
     "--overwrite", 2, "self_run.yaml: is the --config file"),
    ("calibrate-out-exists", "calibrate intrinsics --images {d}/empty --out {d}/calibrated", 2,
     "a calibration is already there"),
    # a folder given as the map was 'map file not found'
    ("map-info-dir", "map info {d}/empty", 2, "empty: is a directory, expected a map file"),
    ("map-plot-dir", "map plot {d}/empty --out {d}/plot.png", 2, "empty: is a directory, expected a map file"),
    ("run-serial-port-missing", "run -c {d}/dxl.yaml --no-camera --no-telemetry --duration 0.2", 3, "/dev/ttyNOPE9"),
    ("run-camera-missing", "run -c {d}/v4l2.yaml --camera --no-telemetry --duration 0.2", 3, "/dev/video99"),
    # send
    ("send-teleop-nan", "send teleop nan 0", 2, "V"),
    ("send-rate", "send teleop 0.1 0 --duration 1 --rate 0", 2, "--rate"),
    ("send-wait", "send estop --wait -1", 2, "--wait"),
    # --wait 0 gave the robot no time to be found: 'does not offer ... may refuse commands' or 'no
    # acknowledgement within 0 s', exit 1, about a robot that takes the command
    ("send-wait-zero", "send estop --wait 0", 2, "argument --wait: expected a number > 0, got '0'"),
    ("send-secret-missing", "send estop --secret-file {d}/nope.key", 2, "nope.key"),
    ("send-endpoint", "send estop --connect garbage", 2, "garbage"),
    ("send-mode", "send mode fly", 2, "fly"),
    ("send-mode-idle-route", "send mode idle --route hall", 2, "--route: mode idle takes no route"),
    ("send-mode-teach-no-route", "send mode teach", 2, "--route: mode teach needs a route (--route NAME"),
    ("send-rate-without-for", "send teleop 0.1 0 --rate 5", 2, "--rate is the rate of a --for S stream"),
    # network options that cannot work were 'cannot connect' (exit 3), a missing TLS file was not named, and
    # TLS options for a tcp/ endpoint were not used
    ("send-user-no-password", "send estop --user bob --password-env VBNAV_TEST_UNSET", 2,
     "--user bob given but $VBNAV_TEST_UNSET is not set"),
    ("send-tls-partial", "send estop --connect tls/127.0.0.1:9 --tls-ca {d}/afile.txt", 2,
     "mutual TLS needs all of --tls-ca, --tls-cert and --tls-key"),
    ("send-tls-missing", "send estop --connect tls/127.0.0.1:9 --tls-ca {d}/nope.pem --tls-cert {d}/afile.txt "
     "--tls-key {d}/afile.txt", 2, "nope.pem: no such file"),
    ("monitor-tls-on-tcp", "monitor --once --connect tcp/127.0.0.1:9 --tls-ca {d}/afile.txt --tls-cert {d}/afile.txt "
     "--tls-key {d}/afile.txt", 2, "--connect tcp/127.0.0.1:9 is not a TLS link"),
    ("route-pull-tls-dir", "route pull r1 loop --to {d}/empty --connect tls/127.0.0.1:9 --tls-ca {d}/empty "
     "--tls-cert {d}/afile.txt --tls-key {d}/afile.txt", 2, "empty: is a directory, expected a PEM file"),
    # teach
    ("teach-no-out", "teach", 2, "--out"),
    ("teach-out-file", "teach --out {d}/afile.txt --duration 0.1", 2, "afile.txt"),
    ("teach-out-under-file", "teach --out {d}/afile.txt/route --duration 0.1", 2, "afile.txt"),
    ("teach-out-not-empty", "teach --out {d}/full --duration 0.1", 2, "--overwrite"),
    ("teach-duration", "teach --out {d}/route --duration nan", 2, "--duration"),
    ("teach-record-dir", "teach --out {d}/route --duration 0.1 --record {d}/empty", 2, "--record"),
    ("teach-garbage-config", "teach --out {d}/route -c {d}/garbage.yaml", 2, "garbage.yaml"),
    # taught by teleop with the network closed: nobody could drive it, and it ran until --duration or Ctrl-C
    ("teach-teleop-no-telemetry", "teach --out {d}/route -c {d}/teach_quiet.yaml --duration 0.5", 2,
     "teach_quiet.yaml: controller.teach teleop: takes its commands over the network"),
    # vo
    ("vo-missing", "vo {d}/nope --out {d}/t.txt", 2, "nope"),
    ("vo-file", "vo {d}/afile.txt --out {d}/t.txt", 2, "afile.txt"),
    ("vo-not-a-dataset", "vo {d}/empty --out {d}/t.txt", 2, "empty"),
    ("vo-image-sizes", "vo {d}/sizes --out {d}/t.txt --quiet", 2, "000001.png"),
    ("vo-out-dir", "vo {d}/good --out {d}/empty", 2, "--out"),
    ("vo-out-no-folder", "vo {d}/good --out {d}/nope/t.txt", 2, "nope"),
    ("vo-plot-dir", "vo {d}/good --out {d}/t.txt --plot {d}/empty", 2, "--plot"),
    ("vo-plot-no-ground-truth", "vo {d}/good --out {d}/t_plot.txt --plot {d}/p.png", 2,
     "good has no ground truth to plot against (no poses.txt)"),
    ("vo-nan-focal", "vo {d}/nanfx --out {d}/t.txt", 2, "calib.txt: P0"),
    ("vo-zero-focal", "vo {d}/zerofx --out {d}/t.txt", 2, "calib.txt: P0"),
    ("vo-zero-baseline", "vo {d}/zerobase --out {d}/t.txt", 2, "calib.txt: P1"),
    ("vo-camera-missing", "vo {d}/good --camera {d}/nope.yaml --out {d}/t.txt", 2, "nope.yaml"),
    ("vo-camera-garbage", "vo {d}/good --camera {d}/garbage.yaml --out {d}/t.txt", 2, "garbage.yaml"),
    ("vo-camera-nan-focal", "vo {d}/good --camera {d}/cam_nanfx.yaml --out {d}/t.txt", 2, "cam_nanfx.yaml: fx"),
    ("vo-camera-zero-focal", "vo {d}/good --camera {d}/cam_zerofx.yaml --out {d}/t.txt", 2, "cam_zerofx.yaml: fx"),
    ("vo-camera-cx-outside", "vo {d}/good --camera {d}/cam_cx.yaml --out {d}/t.txt", 2, "cam_cx.yaml: cx"),
    ("vo-camera-zero-baseline", "vo {d}/good --camera {d}/cam_base0.yaml --out {d}/t.txt", 2,
     "cam_base0.yaml: baseline"),
    ("vo-camera-wrong-size", "vo {d}/good --camera {d}/cam_size.yaml --out {d}/t.txt", 2, "000000.png"),
    ("vo-init-stereo-mono", "vo {d}/mono --init stereo --out {d}/t.txt", 2, "image_r"),
    ("vo-init-bogus", "vo {d}/good --init fly --out {d}/t.txt", 2, "--init"),
]


def _texture(seed: int, w: int = W, h: int = H) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (h, w), dtype=np.uint8)


def _sequence(d, name: str, p0: str = K_ROW, p1: str | None = P1_ROW, small: int | None = None) -> None:
    """A 3-frame KITTI-layout sequence; frame ``small`` of the left images is half size."""
    root = d / name
    for side in ("image_l", "image_r") if p1 is not None else ("image_l",):
        (root / side).mkdir(parents=True)
        for i in range(3):
            img = _texture(i)
            if i == small and side == "image_l":
                img = cv2.resize(img, (W // 2, H // 2))
            cv2.imwrite(str(root / side / f"{i:06d}.png"), img)
    (root / "calib.txt").write_text(f"P0: {p0}\n" + (f"P1: {p1}\n" if p1 is not None else ""))


def make_fixtures(d) -> None:
    (d / "empty").mkdir()
    (d / "full").mkdir()
    (d / "full" / "x").write_text("x")
    (d / "afile.txt").write_text("not what was asked for\n")
    (d / "calibrated").mkdir()
    (d / "calibrated" / "camera_opencv.yaml").write_text("%YAML:1.0\n")
    (d / "garbage.yaml").write_text("robot: [\n")
    (d / "unknown.yaml").write_text("robot: {bogus: 1}\n")
    (d / "badnum.yaml").write_text("robot: {wheel_radius: abc}\n")
    (d / "cfg_nanfx.yaml").write_text("camera: {fx: .nan}\n")
    (d / "cfg_inffx.yaml").write_text("camera: {fx: .inf}\n")
    (d / "cfg_cx.yaml").write_text("camera: {cx: 5000}\n")
    (d / "cfg_seed.yaml").write_text("sim: {seed: -1}\n")
    for name in SELF_CONFIGS:
        (d / name).write_text(SELF_CONFIG)
    (d / "teach_quiet.yaml").write_text("sim: {realtime: true}\ncontroller: {teach: teleop}\n"
                                        "telemetry: {enabled: false}\n")
    (d / "dxl.yaml").write_text("robot: {max_wheel_speed: 6.0, max_linear_speed: 0.3}\n"   # the servos' 6 rad/s
                                "camera: {driver: v4l2, options: {device: /dev/video99}}\n"
                                "drive: {driver: dynamixel, options: {port: /dev/ttyNOPE9}}\n")
    (d / "dxl_realtime.yaml").write_text("sim: {realtime: true}\n"
                                         "camera: {driver: v4l2, options: {device: /dev/video99}}\n"
                                         "drive: {driver: dynamixel, options: {port: /dev/ttyNOPE9}}\n"
                                         "robot: {max_wheel_speed: 6.0, max_linear_speed: 0.3}\n")
    (d / "v4l2.yaml").write_text("camera: {driver: v4l2, options: {device: /dev/video99}}\n"
                                 "controller: {kind: idle}\n")
    _sequence(d, "good")
    _sequence(d, "mono", p1=None)
    _sequence(d, "sizes", small=1)
    _sequence(d, "nanfx", p0=K_ROW.replace("50", "nan", 1), p1=P1_ROW.replace("50", "nan", 1))
    _sequence(d, "zerofx", p0=K_ROW.replace("50", "0", 1), p1=P1_ROW.replace("50", "0", 1))
    _sequence(d, "zerobase", p1=K_ROW)
    (d / "cam_nanfx.yaml").write_text(CAMERA.replace("fx: 50", "fx: .nan") + "baseline: 0.1\n")
    (d / "cam_zerofx.yaml").write_text(CAMERA.replace("fx: 50", "fx: 0") + "baseline: 0.1\n")
    (d / "cam_cx.yaml").write_text(CAMERA.replace(f"cx: {W / 2}", "cx: 900") + "baseline: 0.1\n")
    (d / "cam_base0.yaml").write_text(CAMERA + "baseline: 0\n")
    (d / "cam_size.yaml").write_text(CAMERA.replace(f"width: {W}", "width: 640") + "baseline: 0.1\n")
    (d / "stereo.yaml").write_text(STEREO)
    (d / "stereo_nan.yaml").write_text(STEREO.replace("fx: 50", "fx: .nan"))
    (d / "stereo_base0.yaml").write_text(STEREO.replace("baseline: 0.1", "baseline: 0"))
    (d / "stereo_cx.yaml").write_text(STEREO.replace(f"cx: {W / 2}", "cx: -3"))
    (d / "camera_info.yaml").write_text(f"image_width: {W}\nimage_height: {H}\ncamera_matrix: {{rows: 3, cols: 3, "
                                        f"data: [50, 0, 32, 0, 50, 24, 0, 0, 1]}}\ndistortion_model: plumb_bob\n")
    (d / "stereo_2bad.yaml").write_text(STEREO.replace("fx: 50", "fx: abc").replace("baseline: 0.1", "baseline: x"))
    (d / "stereo_1x1.yaml").write_text("width: 1\nheight: 1\nfx: 1\nfy: 1\ncx: 0.5\ncy: 0.5\nbaseline: 0.1\n")
    cv2.imwrite(str(d / "one.png"), np.zeros((1, 1), np.uint8))
    cv2.imwrite(str(d / "one_b.png"), np.full((1, 1), 255, np.uint8))
    cv2.imwrite(str(d / "left.png"), _texture(0))
    cv2.imwrite(str(d / "left_copy.png"), _texture(0))
    (d / "middlebury_calib.txt").write_text("cam0=[50 0 32; 0 50 24; 0 0 1]\ncam1=[50 0 35; 0 50 24; 0 0 1]\n"
                                            "doffs=3\nbaseline=100.0\nwidth=64\nheight=48\nndisp=16\n")
    cv2.imwrite(str(d / "right.png"), _texture(1))
    cv2.imwrite(str(d / "right_big.png"), _texture(1, W + 16, H + 12))


def _run_forked(argvs: list[list[str]]) -> list[subprocess.CompletedProcess]:
    """Each command line in its own process, forked from one interpreter that has imported the command
    line (tests/cli_forks.py): start-up is nearly all of the CPU a refused command costs."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", VBNAV_FORK_TIMEOUT_S="120")
    r = subprocess.run([sys.executable, str(Path(__file__).with_name("cli_forks.py"))], input=json.dumps(argvs),
                       capture_output=True, text=True, timeout=900, env=env)
    assert r.returncode == 0, r.stderr
    return [subprocess.CompletedProcess(argv, o["returncode"], o["stdout"], o["stderr"])
            for argv, o in zip(argvs, json.loads(r.stdout))]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    make_fixtures(d)
    argvs = {case[0]: case[1].format(d=d).split() for case in CASES}
    done = dict(zip(argvs, _run_forked(list(argvs.values()))))
    assert not [p for p in ("demo_out", "route", "calib", "map.json", "seg.json") if (d / p).exists()], \
        "a refused command wrote its output"
    assert all((d / name).read_text() == SELF_CONFIG for name in SELF_CONFIGS), "a configuration was replaced"
    return done


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_an_exit_code(results, case):
    name, _, code, needle = case
    r = results[name]
    both = r.stdout + r.stderr
    assert "Traceback" not in both, both
    assert r.returncode == code, both
    if code == 2:
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1, r.stderr
        assert lines[0].startswith("vbnav"), r.stderr
        assert needle in lines[0], r.stderr
    else:   # a device that is not there: the run's summary names it
        assert needle in both, both


def test_vo_plot_without_ground_truth_is_refused_before_tracking(results):
    """--plot on a dataset without ground truth was skipped without a word after the whole run; now it is
    refused, naming --plot and the dataset, before any tracking (which would print on stdout)."""
    r = results["vo-plot-no-ground-truth"]
    assert r.stderr.startswith("vbnav vo: --plot ") and r.stdout == "", r.stdout + r.stderr


def test_closed_stdout_is_no_traceback():
    """`vbnav ... | head -1` when the reader has gone before we write: no BrokenPipeError traceback,
    and the exit code of a process ended by SIGPIPE."""
    for argv in (["config", "reference"], ["run", "--no-camera", "--duration", "1", "--json"]):
        r_fd, w_fd = os.pipe()
        os.close(r_fd)                      # the reader is gone: every write to stdout fails
        p = subprocess.run(VBNAV + argv, stdout=w_fd, stderr=subprocess.PIPE, text=True, timeout=120)
        os.close(w_fd)
        assert "Traceback" not in p.stderr and "BrokenPipeError" not in p.stderr, p.stderr
        assert p.returncode == 141, p.stderr


def test_run_into_head_is_no_traceback():
    cmd = " ".join(VBNAV + ["run", "--no-camera", "--duration", "1"]) + " 2>&1 | head -1"
    r = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and len(r.stdout.splitlines()) == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stdout + r.stderr


def test_unexpected_exception_is_a_bug_with_its_traceback(monkeypatch, capsys):
    """Anything that is not bad input keeps its traceback and says it is a bug (exit 1)."""
    from vbnav.control import cli
    from vbnav.control.commands import config

    def broken(args):
        raise ZeroDivisionError("boom")
    monkeypatch.setattr(config, "run", broken)
    assert cli.main(["config", "reference"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "ZeroDivisionError: boom" in err and "this is a bug" in err


def test_a_full_disk_is_said_naming_the_file_not_called_a_bug(tmp_path, monkeypatch, capsys):
    """A write that fails for want of space (or a read-only disk) was 'a bug in vbnav' with a traceback and no
    file named: it names the file being written and the reason, exit 1, and the file there is untouched."""
    import errno
    from vbnav.control import cli
    from vbnav.control.line_map_file import save_map
    from vbnav.vision.line_map import LineMap
    save_map(LineMap(), tmp_path / "m.json")
    out = tmp_path / "m.png"
    out.write_bytes(b"the previous plot")
    real_fsync = os.fsync

    def full(fd):
        if not os.path.isdir(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", full)
    code = cli.main(["map", "plot", str(tmp_path / "m.json"), "--out", str(out)])
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 1, err
    assert f"vbnav map: {out}: No space left on device" in err and "bug" not in err and "Traceback" not in err
    assert out.read_bytes() == b"the previous plot" and sorted(p.name for p in tmp_path.iterdir()) == ["m.json",
                                                                                                      "m.png"]
