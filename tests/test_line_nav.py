"""Using the line map: how much of the simulated room it holds, localisation from 2D-3D line
correspondences, the abstraction to objects, the traversability grid and planner, and the map file. One
map of the simulated room, built once per module (60 frames of the 6 m loop, one every 10 cm, true poses,
stereo segments and floor lines)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from line_scenes import (BASELINE, CAM, MOUNT, build_map, footprint_overlap, loop_poses, render_drive, score_map,
                         signed_area, stereo_camera)
from vbnav.control.line_map_file import MapFileError, load_map, save_map
from vbnav.drivers.sim.world import World
from vbnav.vision.geometry import Pose2
from vbnav.vision.line_abstraction import (box_polygons, floor_lines, missing_lines, object_polygons, pinned_ends,
                                          vertical_edges)
from vbnav.vision.line_localise import View, localise
from vbnav.vision.line_segments import detect_segments
from vbnav.vision.nav_grid import GridParams, build_grid, plan
from vbnav.vision.line_map import LineMap, MapParams


LOOP_FRAMES = 60            # 10 cm apart: an edge is in view for a few frames, 0.15 m apart for verification
# The slow loop's pass as `map build` runs it on the simulated robot: every 1 s (AbstractionThread.period_s)
# at its 0.3 m/s (configs/sim_stereo.yaml's script), 0.3 m: every 3rd frame 10 cm apart.
ABSTRACTION_EVERY = 3


@pytest.fixture(scope="module")
def room_drive():
    world = World.room(0)
    drive = render_drive(world, loop_poses(LOOP_FRAMES))
    lmap, _ = build_map(drive, floor=True, abstraction_every=ABSTRACTION_EVERY)
    return world, lmap, drive


@pytest.fixture(scope="module")
def room_map(room_drive):
    return room_drive[:2]


def test_room_map_holds_the_edges_in_view(room_drive):
    """Recall and precision of the loop map against the room's true edges (rules: tests/line_scenes.py).
    Measured: 13 of 16 edges > 0.3 m in view (wall-floor 1/1, box vertical 6/7, box lower and upper edges 6/8),
    12 of the 12 seen from >= 3 distinct viewpoints, endpoints 2.8 mm median / 4.2 cm 95 %, 1.9 % of 369
    verified segments false, since a keyframe with two ridges is decided by the others (2026-12-03, thirteenth
    session: box_b's far top, a wall line 16 cm above it in the third keyframe). Before: 12 of 16 (box lower
    and upper edges 5/8), 11 of the 12, 2.4 mm / 4.4 cm, 1.9 % of 367,
    since vertical lines on a plain face are matched (vision/line_vertical.py,
    2026-12-03, tenth session): eight rooms gain 8 edges, but here box_b's far top lost its measurement
    (sighted in 2 of the 3 keyframes it needs; the third's unique-ridge test failed by 2 %, 21.4 against
    21.9, with its hypothesis 1 cm lower), and a vertical matched on box_a's plain face lies 5.7 cm off its
    corner (the plain matches' disparity error: 0.46 px median, 1.6 px at 90 %, against 0.37 and 1.4 px for
    the confirmed ones; docs/line_map_history.md, tenth session); the 95 % is asserted at the acceptance's
    5 cm. Before: 13 of 16 (wall-floor 1/1, box vertical 6/7, box lower and upper edges 6/8),
    endpoints 1.9 mm median / 0.9 cm 95 %, 1.9 % of 368 verified segments false (2.5 mm / 1.9 cm before a
    frame's observations were all associated with the map as it stood before the frame, 2.9 mm / 2.4 cm,
    1.7 % of 362 before floor lines said what stands on them, vision/line_floor.py); the three missing (box_d's
    corner, box_e's two edges) are seen from fewer than the 3 distinct viewpoints verification needs: 12 of
    the 12 seen from >= 3 viewpoints are mapped (13 of 13 when 3 frames counted as 3 viewpoints) (12 of 16 before the top and lower edges ran between the seen corners and
    were found as ridges in the keyframes' images: box_b's far top). 11 of 16
    before the slow loop posted the footprints' lower edges too (box_b's far face's foot), 10 of 16 and 5/7
    box vertical before the vertical lines' side bands were compared on slanted planes (box_a's far corner);
    on the room's seeds 1-3: 12, 12 and 11 of 16, were 10, 9 and 8 at the start of 2026-12-02
    (benchmarks/line_room.py); 2.0 % before a segment took at
    most one of two parallel lines of one image; 9 of 16 and 4/7 box vertical before the vertical lines of
    vision/line_vertical.py gave box_b's far corner, 8 of 16 before box_b's top hypothesis was measured on its
    corners' lines in the recent keyframes, 7 before two separating viewpoints verified an unambiguous
    candidate). Built as `map build` builds it, with the slow loop's hypotheses. On the denser 120-frame loop (a
    frame every 5 cm, nearer a real robot's 2 cm): 13 of 20 (13 of the 13 seen from >= 3 viewpoints), 1.6 mm /
    2.6 cm, 1.8 % of 556 false (2.7 cm, 548 before the frame's batch association; 1.7 mm / 1.9 cm, 2.4 % before the floor lines' stance; 7.0 cm 95 %
    before: floor texture 8-12 cm in front of the south wall fused into its foot). The acceptance (90 % of the
    edges in view) is met for the edges seen from >= 3 viewpoints in this room, not for all in view, and not
    on every room (benchmarks/line_room.py, seeds 0-7): docs/line_map.md, "Current figures and acceptance"."""
    world, lmap, drive = room_drive
    # The map `map build` makes: the slow loop's hypotheses inserted while it drove (none verified here).
    assert lmap.hypothesis.any()
    sc = score_map(lmap, world, drive)
    assert sc.in_view >= 12 and sum(v[0] for v in sc.by_class.values()) == sc.in_view
    assert sc.mapped >= 13, sc.missing
    assert sc.in_view_verifiable >= 12 and sc.mapped_verifiable == sc.in_view_verifiable, sc.missing
    assert sc.by_class["wall_floor"][1] >= 1 and sc.by_class["box_horizontal"][1] >= 6   # floor lines, box_b's tops and feet
    assert sc.by_class["box_vertical"][1] >= 6, sc.by_class        # box_b's and box_a's far corners: vertical lines
    assert np.median(sc.endpoint_err) <= 0.005 and np.percentile(sc.endpoint_err, 95) <= 0.05     # the acceptance
    assert sc.false_fraction <= 0.035
    drive = render_drive(world, loop_poses(2 * LOOP_FRAMES))
    lmap, _ = build_map(drive, floor=True, abstraction_every=2 * ABSTRACTION_EVERY)
    sc = score_map(lmap, world, drive)
    assert sc.mapped >= 13, sc.missing
    assert sc.mapped_verifiable >= 0.9 * sc.in_view_verifiable, sc.missing
    assert np.median(sc.endpoint_err) <= 0.004 and np.percentile(sc.endpoint_err, 95) <= 0.04    # 2x; acceptance 5 cm
    assert sc.false_fraction <= 0.045


def test_rooms_the_map_was_not_developed_on():
    """World.room seeds 4-7 (the same boxes and walls, other textures; first measured 2026-12-02, after every
    threshold had been set on seeds 0-3), built and scored as the room test's: so a change fitted to seed 0
    fails here. Measured together (benchmarks/line_room.py prints each room): 47 of the 48 edges seen from
    >= 3 viewpoints mapped, endpoints 2.5 mm median / 1.1 cm 95 %, 13 of 1436 verified segments false, since
    a corner joins its box along a foot (2026-12-03, twelfth session: seed 4's box_a's lower edge from its
    whole footprint); 46 of 48 since vertical lines on a plain face are matched (tenth session; box_b's
    corners and box_a's far corner on seeds 4-6). Before: 37 of 48, 2.6 mm median / 1.7 cm 95 % (the acceptance asks 2 cm / 5 cm; 2.7 mm /
    2.1 cm with a line painted on seed 5's box_a 5.5 cm from its corner counted as the corner's), 13 of
    1416 verified segments false (0.9 %; 11 of 1392 before the distinct viewpoints were counted in time
    order on every view); asserted within about 2x. Before floor lines said what stands on
    them (vision/line_floor.py): 37 of 48, 2.9 mm / 5.7 cm, 20 of 1462 false."""
    mapped = verifiable = false = verified = 0
    errs, ious = [], {}
    for seed in (4, 5, 6, 7):
        world = World.room(seed)
        drive = render_drive(world, loop_poses(LOOP_FRAMES))
        lmap, _ = build_map(drive, floor=True, abstraction_every=ABSTRACTION_EVERY)
        sc = score_map(lmap, world, drive)
        polys = [q.footprint for q in object_polygons(lmap.structure()) if len(q.footprint) >= 3]
        for name, _, xz in world.footprints():
            if name in ("box_a", "box_b"):
                ious[seed, name] = max((footprint_overlap(fp, np.asarray(xz, float))[0] for fp in polys), default=0.0)
        mapped, verifiable = mapped + sc.mapped_verifiable, verifiable + sc.in_view_verifiable
        false, verified = false + round(sc.false_fraction * sc.verified), verified + sc.verified
        errs.append(sc.endpoint_err)
    err = np.concatenate(errs)
    assert verifiable >= 44 and mapped >= 44, (mapped, verifiable)
    assert np.median(err) <= 0.005 and np.percentile(err, 95) <= 0.025, (np.median(err), np.percentile(err, 95))
    assert false <= 0.02 * verified, (false, verified)
    # The two boxes inside the loop, the goto grid's obstacles: IoU 0.98-0.99 each (seed 4's box_a 0.25 before
    # a corner joined its box along a foot, whatever its top; line_abstraction._face_between).
    assert min(ious.values()) >= 0.9, ious


def test_without_verification_the_glimpsed_edges_stay_out_and_the_map_fails_its_accuracy(room_drive):
    """Why the room's coverage is read against the edges seen from >= 3 viewpoints: the edges in view from
    fewer (seed 0: box_d's corner, in one frame at 2.8 m by the image's right border; box_e's two top edges,
    in two frames 10 cm apart at 2.7-3.0 m, cut by that border) are not matched by the stereo in the frames
    that glimpse them, so a map that takes every observation as verified (``verify_views`` 1) maps no more
    edges, and it fails the acceptance's accuracy. Measured (benchmarks/line_room.py --unverified, 2026-12-04):
    seed 0 13 of 16 edges either way, the unverified map's endpoints 4.6 mm / 33 cm 95 %, 7.2 % of 1522
    segments false (the verified map 2.8 mm / 4.2 cm, 1.9 % of 369); eight rooms 98 of 128 against 100 of 128,
    7.9 cm and 7.2 % false at 60 frames, 8.9 cm and 9.1 % at 180. Asserted: no more edges, and over the
    acceptance's 5 cm and 5 %."""
    world, lmap, drive = room_drive
    verified = score_map(lmap, world, drive)
    naive, _ = build_map(drive, map_params=MapParams(verify_views=1), floor=True, abstraction_every=ABSTRACTION_EVERY)
    sc = score_map(naive, world, drive)
    assert sc.in_view == verified.in_view and sc.mapped <= verified.mapped, (sc.missing, verified.missing)
    assert sc.false_fraction > 0.05 and sc.verified >= 2 * verified.verified, (sc.false_fraction, sc.verified)
    assert np.percentile(sc.endpoint_err, 95) > 0.05, np.percentile(sc.endpoint_err, 95)


VIEW = View(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT)


@pytest.mark.parametrize("true", [Pose2(-0.3, -1.5, 2.5), Pose2(0.0, -1.3, -2.5)])
def test_localisation_from_a_new_start_pose(room_map, true):
    world, lmap = room_map
    f = stereo_camera(world, seed=7).render_frame(true, seq=99)
    guess = Pose2(true.x + 0.2, true.z - 0.15, true.theta + math.radians(8))    # 25 cm, 8 deg off
    r = localise(lmap, detect_segments(f.image), VIEW, guess)
    err = math.hypot(r.pose.x - true.x, r.pose.z - true.z)
    dth = math.degrees(abs(math.remainder(r.pose.theta - true.theta, math.tau)))
    # Acceptance: 3 cm and 1 degree (measured 0.2-2.5 cm, 0.03-0.6 deg).
    assert err < 0.03 and dth < 1.0, (err, dth, r)
    assert r.matches >= 3


def test_localisation_from_random_start_poses_is_right_when_it_says_ok(room_map):
    """16 random poses in the room, each guessed 25 cm / 8 deg off. Facing parts of the room the loop saw
    little of, the pose is often not found; then it must say so instead of reporting a wrong pose.
    Measured: 8 ok, 7 of them within 3 cm / 1 deg, the other 7.8 cm / 2.0 deg; without the explained-share
    rule 5 wrong poses (4-86 cm off) said ok."""
    world, lmap = room_map
    rng = np.random.default_rng(0)
    cam = stereo_camera(world, seed=7)
    ok, good = 0, 0
    for k in range(16):
        true = Pose2(rng.uniform(-0.8, 0.8), rng.uniform(-1.8, 0.8), rng.uniform(-math.pi, math.pi))
        f = cam.render_frame(true, seq=100 + k)
        guess = Pose2(true.x + 0.2, true.z - 0.15, true.theta + math.radians(8))
        r = localise(lmap, detect_segments(f.image), VIEW, guess)
        err = math.hypot(r.pose.x - true.x, r.pose.z - true.z)
        dth = math.degrees(abs(math.remainder(r.pose.theta - true.theta, math.tau)))
        if r.ok:
            ok += 1
            good += err < 0.03 and dth < 1.0
            assert err < 0.15 and dth < 4.0, (k, err, dth, r)   # never a wrong pose reported ok
    assert ok >= 4 and good >= 4, (ok, good)


def test_localisation_reports_a_blank_view():
    lmap = LineMap()
    from vbnav.vision.line_segments import Segments2D
    r = localise(lmap, Segments2D(np.zeros((0, 4)), np.zeros((0, 2))), VIEW, Pose2())
    assert not r.ok and r.matches == 0


def test_abstraction_finds_box_corners_and_hypotheses():
    # A 0.8 x 0.6 x 0.9 m box seen at three vertical corners.
    corners = np.array([[0.0, 0.0], [0.8, 0.0], [0.8, 0.6]])
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners])
    edges = vertical_edges(P)
    assert len(edges) == 3 and np.allclose(edges[:, 2], 0.9)
    polys = box_polygons(edges)
    assert len(polys) == 1 and polys[0].corners == 3
    # The footprint is the whole rectangle: the unseen corner is occupied too.
    assert len(polys[0].footprint) == 4 and np.isclose(abs(signed_area(polys[0].footprint)), 0.48)
    hyp = missing_lines(polys[0])
    assert np.allclose(hyp[0], [[0.0, 0.0, 0.6], [0.0, -0.9, 0.6]])     # the fourth corner
    assert len(hyp) == 9                                                # and the four top and lower edges
    assert np.allclose(hyp[5:, :, 1], 0.0) and np.allclose(hyp[1:5, :, 1], -0.9)
    lmap = LineMap()
    ids = lmap.add_hypotheses(hyp)
    assert len(ids) == len(hyp) and lmap.hypothesis.all() and not lmap.verified.any()


def test_a_corner_whose_top_ended_early_joins_its_box_along_the_foot_of_their_face():
    """A corner's top is where LSD's pieces of it ended (room seeds 3 and 4 at 60 frames: box_a's near corner
    at 0.36-0.56 m of its 0.9 m, so it made an object of its own or none, IoU 0.25). A foot lying between it
    and another corner joins them whatever their tops; a tall line beyond the box on that face's line, and
    corners with no foot between them, are not joined."""
    corners = np.array([[0.0, 0.0], [0.8, 0.0], [0.8, 0.6]])
    tops = [0.9, 0.36, 0.9]                                   # the middle corner's pieces ended early
    vertical = [[[x, 0.0, z], [x, -h, z]] for (x, z), h in zip(corners, tops)]
    wall_line = [[[1.2, 0.0, 0.0], [1.2, -2.0, 0.0]]]         # a tall line 0.4 m past the box, on its face's line
    feet = [[[0.15, 0.0, 0.01], [0.6, 0.0, -0.01]],           # a piece of the south face's foot
            [[0.81, 0.0, 0.1], [0.79, 0.0, 0.45]]]            # and of the east face's
    P = np.array(vertical + wall_line + feet, float)
    polys = object_polygons(P)
    box = [q for q in polys if q.corners == 3]
    assert len(box) == 1 and np.isclose(abs(signed_area(box[0].footprint)), 0.48, atol=0.01), \
        [(q.corners, q.footprint.round(2).tolist()) for q in polys]
    assert all(q.footprint[:, 0].max() < 1.0 for q in polys)  # the tall line stays out of it
    # Without the feet the low corner is an object of its own (or none): tops 0.54 m apart prove nothing
    # either way, and nothing else joins it.
    alone = object_polygons(np.array(vertical + wall_line, float))
    assert not any(q.corners == 3 for q in alone)


def test_abstraction_closes_a_box_seen_at_two_corners_and_its_foot():
    """Two vertical edges of one face and the floor line of the other face (vision/line_floor.py) close
    the box; floor texture ending near a corner (one vertical edge on it) does not stretch it."""
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in [(0.0, 0.0), (0.8, 0.0)]]
                 + [[[0.8, 0.0, 0.0], [0.8, 0.0, 0.6]],          # the side face's foot, from a seen corner
                    [[0.0, 0.0, 0.0], [-0.5, 0.0, -0.4]],        # floor texture ending at a corner, oblique
                    [[0.0, -0.9, 0.0], [0.8, -0.9, 0.0]]])       # the top edge: not on the floor
    assert len(floor_lines(P)) == 2
    polys = object_polygons(P)
    assert len(polys) == 1 and polys[0].corners == 2
    fp = polys[0].footprint
    assert len(fp) == 4 and np.isclose(abs(signed_area(fp)), 0.48)
    assert np.allclose(sorted(map(tuple, fp.round(6))), [(0.0, 0.0), (0.0, 0.6), (0.8, 0.0), (0.8, 0.6)])
    hyp = missing_lines(polys[0])
    assert len(hyp) == 2 + 4 + 4                                        # two unseen corners, four top and lower edges


def test_top_and_lower_edge_hypotheses_run_between_the_seen_corners():
    """The footprint is a rectangle fitted to the seen corners, a few cm off each; a top or lower edge
    hypothesis ran between the rectangle's vertices, so its line in a keyframe lay up to 20 px off the edge
    at 0.6 m and its ridge was not found (room seed 0: box_b's far top; seed 3). Its ends are now the seen
    corners' (the unseen corner's the rectangle's): room seeds 0-3 46 -> 48 of 64 edges."""
    corners = [(0.0, 0.0), (0.81, 0.03), (0.8, 0.6)]          # one corner 3 cm off the others' rectangle
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners])
    poly = object_polygons(P)[0]
    hyp = missing_lines(poly)
    ends = hyp[1:].reshape(-1, 3)[:, [0, 2]]                  # the tops' and lower edges' ends
    for c in corners:
        assert np.linalg.norm(ends - c, axis=1).min() < 1e-9, c
    assert len(hyp) == 9 and np.linalg.norm(hyp[0, 0, [0, 2]] - [0.0, 0.6]) < 0.05    # the unseen corner
    # The ends at seen corners are pinned; the unseen corner's are checked when the edge is sighted.
    pinned = pinned_ends(hyp, poly)
    unseen = np.linalg.norm(hyp[..., [0, 2]] - hyp[0, 0, [0, 2]], axis=2) < 1e-9
    assert pinned[1:].sum() == 12 and np.array_equal(pinned[1:], ~unseen[1:])


def test_a_narrow_footprint_gives_no_edge_of_zero_length():
    """Two corners of a footprint 12 cm wide lie within corner_seen_m (15 cm) of one seen corner: both were
    moved onto it, and the edge between them had zero length. `goto --map-out` then refused to save the
    grown map (it could not be loaded back: segments[1106] p0 == p1; the full simulated robot behind box_b).
    A seen corner moves only its nearest footprint corner, and the map takes no hypothesis shorter than
    min_length_m."""
    corners = [(0.0, 0.0), (0.8, 0.0), (0.8, 0.12)]
    P = np.array([[[x, 0.0, z], [x, -0.5, z]] for x, z in corners])
    hyp = missing_lines(object_polygons(P)[0])
    lengths = np.linalg.norm(hyp[:, 1] - hyp[:, 0], axis=1)
    assert lengths.min() >= 0.1, np.round(hyp, 3)
    lmap = LineMap()
    ids = lmap.add_hypotheses(np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]]))
    assert len(ids) == 1 and len(lmap) == 1


def test_vertical_texture_lines_on_a_face_do_not_turn_the_footprint():
    """Room seed 3: box_b's verified vertical edges were its three seen corners (one 3 cm off) and two
    texture lines on its faces (2-3 cm off the faces' lines). As hull vertices they split each face in two,
    no hull corner was within 15 deg of a right angle, and the smallest rectangle ran across the box's
    diagonal (IoU with the true footprint 0.34; the goto grid's box turned 45 deg). Hull vertices within
    ``foot_on_m`` of their neighbours' line are on a face and are dropped: the footprint is the box's."""
    verticals = [(1.78, -0.58), (1.02, 0.18), (1.23, -0.69), (1.17, -0.56), (1.41, -0.68)]
    P = np.array([[[x, 0.0, z], [x, -0.5, z]] for x, z in verticals])
    polys = object_polygons(P)
    assert len(polys) == 1
    true = np.array([(1.02, 0.18), (1.2, -0.7), (1.78, -0.58), (1.6, 0.3)], np.float32)
    fp = polys[0].footprint
    iou = footprint_overlap(fp, true)[0]
    assert iou >= 0.9, (iou, fp)                        # measured 0.92 (0.35 before)


def _footprint_iou(fp: np.ndarray, true: np.ndarray) -> float:
    return footprint_overlap(fp, true)[0]


BOX_B = np.array([(1.02, 0.18), (1.2, -0.7), (1.78, -0.58), (1.6, 0.3)])
BOX_A = np.array([(-1.77, 0.13), (-1.01, -0.1), (-0.83, 0.47), (-1.59, 0.69)])


def test_a_floor_line_leaving_the_line_between_two_texture_lines_is_not_a_foot():
    """Room seed 1, 120 frames: box_b's verified vertical edges were its three seen corners and three texture
    lines on its faces, and a floor line 0.46 m long left one texture line at right angles to the line
    between two texture lines on adjacent faces (across the box, no face). Taken as the other face's foot,
    its end 0.3 m outside the box turned the footprint 45 deg (IoU 0.30). A face is a side of the seen
    corners (all of them on one side of it) and the foot starts at one of its ends: the footprint is the
    box's. A foot at right angles to a real face, from its end corner, still closes the box."""
    verticals = [(1.784, -0.582), (1.016, 0.181), (1.189, -0.672), (1.118, -0.321), (1.655, -0.609),
                 (1.167, -0.562)]
    P = np.array([[[x, 0.0, z], [x, -0.45, z]] for x, z in verticals]
                 + [[[1.208, 0.0, -0.7], [1.832, 0.0, -0.569]],        # the south face's foot
                    [[1.013, 0.0, 0.202], [1.189, 0.0, -0.672]],       # the west face's foot
                    [[1.648, 0.0, -0.612], [1.377, 0.0, -0.986]]])     # floor texture meeting the south face
    polys = object_polygons(P)
    assert len(polys) == 1
    assert _footprint_iou(polys[0].footprint, BOX_B) >= 0.9, polys[0].footprint      # measured 0.98 (0.30 before)
    # Two corners of the south face and the east face's foot from its end corner: the box is closed.
    P = np.array([[[x, 0.0, z], [x, -0.45, z]] for x, z in [(1.2, -0.7), (1.78, -0.58)]]
                 + [[[1.78, 0.0, -0.58], [1.6, 0.0, 0.3]]])
    polys = object_polygons(P)
    assert len(polys) == 1 and _footprint_iou(polys[0].footprint, BOX_B) >= 0.95, polys[0].footprint


def test_a_floor_line_touching_one_corner_twice_is_not_a_foot():
    """The map grown in `goto --map` (seed 0, from (-0.9, -1.5)) held box_a's north-east corner as two
    vertical edges 7 cm apart (more than merge_m), and a floor texture line from that corner, 26 deg off
    the face, passed within foot_on_m of both: counted as a foot between two corners, its far end ran the
    footprint 0.86 m off the box to within 0.23 m of the goal, and the route was held for good. A foot's
    corners must stand min_side_m apart along it."""
    corners = [(-1.64, 0.09), (-0.83, 0.45), (-1.07, -0.09), (-1.01, -0.11), (-0.83, 0.38)]
    heights = [0.93, 0.91, 0.88, 0.88, 0.63]
    P = np.array([[[x, 0.0, z], [x, -h, z]] for (x, z), h in zip(corners, heights)]
                 + [[[0.03, 0.0, 0.54], [-0.83, 0.0, 0.41]],        # the texture line, touching the corner
                    [[-0.82, 0.0, 0.49], [-1.0, 0.0, -0.11]],       # box_a's east foot, corner to corner
                    [[-1.76, 0.0, 0.12], [-1.01, 0.0, -0.1]]])      # its south foot
    polys = object_polygons(P)
    assert len(polys) == 1
    fp = polys[0].footprint
    assert fp[:, 0].max() < -0.75, fp                                # was 0.03: the texture line's end
    assert footprint_overlap(fp, BOX_A)[1] >= 0.95 and _footprint_iou(fp, BOX_A) >= 0.85, fp


def test_a_foot_running_past_a_corner_does_not_turn_the_footprint():
    """Room seed 2, 120 frames: box_a's three seen corners meet at a right angle at (-1.01, -0.1), and its
    east face's foot ran on 0.2 m past that corner (LSD joining it to the floor's texture). The end, a hull
    vertex, hid the corners' right angle and the rectangle turned (IoU 0.62, part of the box outside it).
    The seen corners' own right angle now sets the sides; every point stays inside, so the footprint is
    longer by the overshoot (IoU 0.73) but follows the faces and holds the whole box (the grid's obstacle
    errs on the safe side). A foot past a texture line on a face reaches the corner not seen."""
    corners = [(-1.77, 0.13), (-0.83, 0.47), (-1.01, -0.1)]
    P = np.array([[[x, 0.0, z], [x, -0.8, z]] for x, z in corners]
                 + [[[-1.064, 0.0, -0.3], [-0.834, 0.0, 0.472]]])
    polys = object_polygons(P)
    assert len(polys) == 1
    fp = polys[0].footprint
    face = math.degrees(math.atan2(0.47 + 0.1, -0.83 + 1.01))
    for d in np.roll(fp, -1, axis=0) - fp:                      # each side along a face, or across
        off = abs(math.remainder(math.degrees(math.atan2(d[1], d[0])) - face, 90.0))
        assert off <= 2.0, (off, fp)                                # measured 0.7 deg (14 deg before)
    assert footprint_overlap(fp, BOX_A)[1] >= 0.99                   # the whole box is inside
    assert _footprint_iou(fp, BOX_A) >= 0.7, fp                      # measured 0.73
    # A corner, a texture line 0.4 m along the face and the other face's corner: the face's foot runs on to
    # 0.8 m, where the corner not seen is.
    P = np.array([[[x, 0.0, z], [x, -0.8, z]] for x, z in [(0.0, 0.0), (0.4, 0.0), (0.0, 0.6)]]
                 + [[[0.0, 0.0, 0.0], [0.8, 0.0, 0.0]]])
    fp = object_polygons(P)[0].footprint
    assert np.isclose(fp[:, 0].max(), 0.8) and np.isclose(abs(signed_area(fp)), 0.48), fp


def test_a_lower_edge_ending_at_a_corner_keeps_the_corners_right_angle():
    """A box's lower edge (a floor line) ending 1.5 cm from a corner, a few mm outside the hull of the
    corners (the room loop's box_b at 120 frames): its end is that corner, not a hull vertex of its own, so
    the corner's right angle still sets the footprint's axes (it was skipped as a side under
    ``min_side_m``, and the smallest rectangle took the hypotenuse of the three corners as a side)."""
    corners = [(0.0, 0.0), (0.8, 0.0), (0.8, 0.6)]
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners]
                 + [[[0.785, 0.0, -0.003], [0.3, 0.0, -0.003]]])     # the foot of face (0,0)-(0.8,0)
    polys = object_polygons(P)
    assert len(polys) == 1
    fp = polys[0].footprint
    assert len(fp) == 4 and np.isclose(abs(signed_area(fp)), 0.8 * 0.603, atol=0.01)
    assert np.abs(np.sort(fp[:, 0]) - [0.0, 0.0, 0.8, 0.8]).max() < 0.02, fp     # sides along the faces
    assert np.abs(np.sort(fp[:, 1]) - [-0.003, -0.003, 0.6, 0.6]).max() < 0.02, fp


def test_planner_goes_around_a_mapped_box():
    # A box footprint between start and goal: the path keeps the robot radius from it.
    poly = np.array([[-0.4, -0.3], [0.4, -0.3], [0.4, 0.3], [-0.4, 0.3]])
    grid = build_grid(np.zeros((0, 2, 3)), GridParams(), extra_points=np.array([[0, -2], [0, 2]]), polygons=[poly])
    path = plan(grid, (0.0, -1.5), (0.0, 1.5))
    assert path is not None and len(path) >= 3
    pts = np.concatenate([np.linspace(a, b, 50) for a, b in zip(path, path[1:])])
    outside = np.maximum(np.abs(pts[:, 0]) - 0.4, np.abs(pts[:, 1]) - 0.3)
    assert outside.min() >= 0.2
    assert plan(grid, (0.0, -1.5), (0.0, 0.0)) is None                    # goal inside the box


def test_room_map_grid_plans_behind_box_a(room_map):
    """box_a is seen from the loop at its south and east faces only; its footprint is closed from its
    vertical edges and lower edges (hypothesised corner), so the plans go around the whole box."""
    world, lmap = room_map
    V = lmap.P[lmap.verified]
    polys = [p.footprint for p in object_polygons(V)]
    box_a = [q for q in polys if np.hypot(*(q.mean(axis=0) - (-1.3, 0.3))) < 0.5]
    assert len(box_a) == 1 and len(box_a[0]) == 4
    # The true footprint (0.48 m^2) is inside the mapped one give or take 0.2 m, which the grid's growth by
    # the radius + 8 cm covers (measured: 0.59 m^2 with the unseen corner 10 cm outside; with the half-size
    # LSD of the fast loop 0.39 m^2, the west corners 14 cm outside: the lower edge is seen shorter).
    true_a = np.array([[-0.83, 0.47], [-1.59, 0.70], [-1.77, 0.13], [-1.01, -0.10]])
    assert 0.3 <= abs(signed_area(box_a[0])) <= 1.2
    assert all(_inside(box_a[0], c, 0.2) for c in true_a)
    goal = (-1.3, 1.2)                        # north of box_a: seen from the loop, never visited
    grid = build_grid(V, GridParams(), extra_points=np.array([goal, (0.0, -2.3)]), polygons=polys)
    for start in [(0.0, -2.25), (0.8, -1.0), (-0.9, -1.5)]:
        path = plan(grid, start, goal)
        assert path is not None, start
        pts = np.concatenate([np.linspace(a, b, 40) for a, b in zip(path, path[1:])])
        clear = min(world.clearance(x, z) for x, z in pts)
        assert clear > GridParams().robot_radius_m, (start, clear, path)   # never touches box or wall


# Start poses (x, z, heading deg) south, east and west of box_a: the first two never see behind it, the third
# stands beside it; the goal north of it was seen from the loop, never visited.
GOTO_STARTS = [(0.0, -2.25, -20.0), (0.8, -1.0, -60.0), (-0.9, -1.5, 10.0)]
GOTO_GOAL = (-1.3, 1.2, 0.0)


@pytest.mark.parametrize("start", GOTO_STARTS)
def test_goto_on_the_room_map_drives_behind_box_a_without_touching_it(room_map, tmp_path, start):
    """What `vbnav goto --map` does (control/commands/goto.py: plan on the saved map, waypoints into the
    reference frame, the goto controller) on a unicycle localised by VSLAM fixes (the truth, 30 ms old) and
    biased odometry: it arrives, and the robot's disc (radius 0.2 m) never touches a wall or box. The full
    simulated robot (camera, VSLAM, obstacle stop) from the three starts: benchmarks/goto_replan.py
    (planned once 1.2 / 1.1 / 0.6 cm, closest approach 0.351 / 0.404 / 0.334 m; re-planning as the map
    grows 1.2 / 1.2 / 0.7 cm, 0.373 / 0.402 / 0.386 m)."""
    from test_vslam_nav import Unicycle

    from vbnav.control.map_planning import map_route_in_reference_frame, plan_on_map
    from vbnav.control.config.vslam import GotoConfig
    from vbnav.control.controllers.goto import GotoController
    world, lmap = room_map
    path = tmp_path / "room.json"
    save_map(lmap, path)
    s = Pose2(start[0], start[1], math.radians(start[2]))
    g = Pose2(GOTO_GOAL[0], GOTO_GOAL[1], math.radians(GOTO_GOAL[2]))
    planned = plan_on_map(str(path), s, g, 0.2)
    assert planned is not None and len(planned) >= 3           # around the box, not straight through it
    waypoints, goal_ref = map_route_in_reference_frame(planned, s, g)
    ctrl = GotoController(goal_ref, GotoConfig(), waypoints=waypoints, follow_route=True)
    sim = Unicycle(s, odom_scale=1.03, odom_drift=0.03)
    sim.run(ctrl, seconds=60.0)
    assert ctrl.finished, ctrl.status()
    assert math.hypot(sim.true.x - g.x, sim.true.z - g.z) < 0.02           # measured 1.0 cm
    clearance = min(world.clearance(t.x, t.z) for _, t, _ in sim.history[::5])
    assert clearance > 0.2, (clearance, planned)        # measured 0.41-0.46 m


def _inside(poly: np.ndarray, p, margin: float = 0.05) -> bool:
    """p within ``margin`` of the convex polygon (either orientation)."""
    import cv2
    return cv2.pointPolygonTest(poly.astype(np.float32), (float(p[0]), float(p[1])), True) >= -margin


def test_map_file_round_trip_and_errors(room_map, tmp_path):
    _, lmap = room_map
    p = tmp_path / "room.json"
    save_map(lmap, p, {"world": "room"})
    back, meta = load_map(p)
    assert meta == {"world": "room"} and len(back) == len(lmap)
    assert np.allclose(back.P, lmap.P, atol=1e-5) and (back.verified == lmap.verified).all()
    assert (back.ambiguous == lmap.ambiguous).all() and lmap.ambiguous.any() and not lmap.ambiguous.all()
    assert [len(v) for v in back.views] == [len(v) for v in lmap.views]
    data = json.loads(p.read_text())
    data["params"]["verify_vievs"] = 2                  # a parameter this vbnav would not apply: refused
    p.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match=r"room.json: params: unknown key\(s\) 'verify_vievs'"):
        load_map(p)
    del data["params"]["verify_vievs"]
    data["version"] = 99
    p.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match="newer"):
        load_map(p)
    p.write_text("{}")
    with pytest.raises(MapFileError, match="not a vbnav line map"):
        load_map(p)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["params"].update(max_range_m="far"), r"params: max_range_m: expected a finite number, got 'far'"),
    (lambda d: d["params"].update(verify_views=2.5), r"params: verify_views: expected a finite integer, got 2.5"),
    (lambda d: d["segments"][0].update(views=[[1.0, 2.0]]), r"segments\[0\].views: expected \[x, y, z, heading\]"),
    (lambda d: d["segments"][0].update(cov0=[[float("nan")] * 3] * 3), r"segments\[0\]\.cov0: expected a 3x3 matrix of finite numbers"),
    (lambda d: d.update(meta=[1]), "meta: expected an object with a list 'objects'"),
    (lambda d: d.update(meta={"objects": [{"footprint": "abc", "height": 1}]}), r"meta.objects\[0\]: expected"),
    (lambda d: d.update(version=True), "version must be an integer >= 1, got True"),
], ids=["param-word", "param-int", "views-shape", "cov-nan", "meta-list", "object-footprint", "version-bool"])
def test_a_malformed_map_file_is_refused_at_load_naming_the_field(room_map, tmp_path, edit, match):
    """Wrong parameter types and view shapes loaded, then failed the first mapping frame of a goto --map
    (a safety trip naming no file); a malformed meta was a traceback of map info and goto; NaN covariances
    loaded. Now load_map refuses each, naming the file and the field."""
    _, lmap = room_map
    p = tmp_path / "room.json"
    save_map(lmap, p, {"world": "room"})
    data = json.loads(p.read_text())
    edit(data)
    p.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match="room.json: " + match):
        load_map(p)


def test_map_build_info_plot_commands(tmp_path, capsys):
    from vbnav.control.cli import main
    out, png = tmp_path / "m.json", tmp_path / "m.png"
    assert main(["map", "build", "-c", "sim_stereo", "--out", str(out), "--duration", "0.4"]) == 0
    assert "verified segments" in capsys.readouterr().out
    from vbnav.control.config import load_config
    assert json.loads(out.read_text())["meta"]["sim_start_pose"] == load_config("sim_stereo").sim.start_pose
    assert main(["map", "info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] >= 4 and info["segments"] > 0
    assert main(["map", "plot", str(out), "--out", str(png), "--all"]) == 0
    assert png.stat().st_size > 1000
    assert main(["map", "info", str(tmp_path / "missing.json")]) == 2
    assert "map file not found" in capsys.readouterr().err


def test_abstraction_thread_posts_hypotheses_the_sensor_loop_inserts():
    import time

    from vbnav.control.stages.line_map import LineMapStage
    lmap = LineMap()
    corners = np.array([[0.0, 2.0], [0.8, 2.0], [0.8, 2.6]])
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners])
    lmap._insert(P, np.broadcast_to(1e-4 * np.eye(3), (3, 2, 3, 3)).copy(), np.full(3, -1), np.zeros(4))
    lmap.verified[:] = True
    stage = LineMapStage(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT, lmap=lmap,
                         abstraction_period_s=0.01)
    stage.start()                                     # the slow loop in its own thread
    try:
        deadline = time.monotonic() + 5.0
        while stage.abstraction.runs < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stage.stop()
    assert stage.abstraction.runs >= 2 and len(stage.abstraction.polygons) == 1
    assert stage.abstraction.hypotheses.qsize() == 1           # one object's hypotheses, posted once
    stage._drain_hypotheses()                                  # what process() does before each frame
    assert stage.stats["hypotheses_in"] == 9 and lmap.hypothesis.sum() == 9     # a corner, 4 tops, 4 lower edges
    # Hypotheses are predicted (to be verified in view) and pruned by misses like any candidate.
    from vbnav.vision.geometry import camera_pose
    R, t = camera_pose(Pose2(0.4, 0.0, -math.radians(70.0)), MOUNT)     # the head (yaw 70 deg) looks along +z
    pred = lmap.predict(R, t, CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, CAM.width, CAM.height)
    assert np.isin(np.nonzero(lmap.hypothesis)[0], pred.index).any()


def test_goto_map_refuses_unreachable_goal_and_start_without_map(tmp_path, capsys):
    from vbnav.control.cli import main
    # A closed square of 1 m high walls around (0, 3): a goal inside cannot be reached.
    sq = [(-0.5, 2.5), (0.5, 2.5), (0.5, 3.5), (-0.5, 3.5)]
    P = np.array([[[a[0], -0.5, a[1]], [b[0], -0.5, b[1]]] for a, b in zip(sq, sq[1:] + sq[:1])])
    lmap = LineMap()
    lmap._insert(P, np.broadcast_to(1e-4 * np.eye(3), (4, 2, 3, 3)).copy(), np.full(4, -1), np.zeros(4))
    lmap.verified[:] = True
    path = tmp_path / "box.json"
    save_map(lmap, path)
    assert main(["goto", "--map", str(path), "--goal", "0", "3", "0"]) == 1
    assert "no path" in capsys.readouterr().err
    assert main(["goto", "--start", "0", "0", "0", "--goal", "0", "3", "0"]) == 2
    assert "--start need(s) --map" in capsys.readouterr().err
    assert main(["goto", "--map-out", str(tmp_path / "out.json"), "--goal", "0", "3", "0"]) == 2
    assert "--map-out need(s) --map" in capsys.readouterr().err
    # --robot-radius only grows the map's planning grid: without --map it was accepted and ignored
    assert main(["goto", "--robot-radius", "0.5", "--goal", "0", "3", "0"]) == 2
    assert "--robot-radius need(s) --map" in capsys.readouterr().err
    assert main(["goto", "--map", str(path), "--static-map", "--map-out", str(tmp_path / "o.json"), "--goal", "0",
                 "3", "0"]) == 2
    assert "--map-out needs the map to grow" in capsys.readouterr().err


def test_goto_map_localises_its_start_against_the_map(room_map, tmp_path, capsys):
    """`vbnav goto --map MAP --localise`: the simulated robot stands at a pose of the mapped room; --start is
    only a guess 25 cm / 8 deg off, and the first stereo frame puts the robot where it is (measured 0.6 cm /
    0.13 deg for this pose). A guess the map cannot confirm (facing a wall it never saw) exits 1 and says so."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR
    world, lmap = room_map
    path = tmp_path / "room.json"
    save_map(lmap, path)
    true = Pose2(-0.3, -1.5, 2.5)
    cfg = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    cfg["camera"]["mount"]["yaw_deg"] = math.degrees(MOUNT.yaw)       # the mapping head's mount
    cfg["sim"]["start_pose"] = [true.x, true.z, math.degrees(true.theta)]
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    guess = [true.x + 0.2, true.z - 0.15, math.degrees(true.theta) + 8.0]
    args = ["goto", "-c", str(tmp_path / "robot.yaml"), "--map", str(path), "--localise", "--goal", "-0.3", "-1.0",
            "0", "--duration", "0.2", "--start", *map(str, guess)]
    main(args)
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("localised against the map:"))
    x, z, th = (float(line.split(k + "=")[1].split()[0]) for k in ("x", "z", "theta"))
    assert math.hypot(x - true.x, z - true.z) < 0.03 and abs(th - math.degrees(true.theta)) < 1.0, line
    cfg["sim"]["start_pose"] = [0.0, 0.5, 0.0]                          # facing the unmapped north wall
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    assert main(args[:-3] + ["0.0", "0.5", "0.0"]) == 1
    assert "the map does not confirm a start pose" in capsys.readouterr().err
    cfg["sim"]["start_pose"] = [0.0, 2.5, 0.0]                          # a metre from it: 5 mapped lines in view
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    assert main(args[:-3] + ["0.0", "2.5", "0.0"]) == 1
    err = capsys.readouterr().err
    # "1 of the 5 map segments predicted in view found, inf px rms" said nothing of why
    assert "map segments predicted in view found, fewer than the 8 a pose needs" in err and "inf" not in err, err
    cfg["sim"]["start_pose"] = [3.5, 2.5, 45.0]                         # facing the room's far corner
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    assert main(args[:-3] + ["3.5", "2.5", "45.0"]) == 1
    err = capsys.readouterr().err
    assert "no map segment would be in view from the poses searched around --start (0.3 m / 12 deg)" in err, err


@pytest.mark.parametrize("bad", ["no-right", "half-size", "uint16", "nan-odometry"])
def test_line_map_stage_skips_a_frame_it_cannot_use(bad):
    """A frame without its right image raised ValueError ('the line map needs a stereo pair'), which ends the run;
    a half-size frame was mapped with the intrinsics of the full size; a 16-bit pair was mapped as if 8-bit; a frame
    at a NaN odometry pose fused its segments into the map at a NaN pose. Each is now not ok, saying why, the map is
    left as it is, and the frames after it are mapped again."""
    from vbnav.control.stages.line_map import LineMapStage
    from vbnav.drivers.camera import Frame

    poses = loop_poses(60)[:8]
    drive = render_drive(World.room(seed=1), poses)
    stage = LineMapStage(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT,
                         abstraction_period_s=None)
    results = []
    for i, (f, p) in enumerate(zip(drive.frames, poses)):
        if i == 4:
            before = (stage.revision, stage.stats["frames"], len(stage.map))
            if bad == "no-right":
                f = Frame(f.image, f.stamp_ns, f.seq, disparity=f.disparity, meta=f.meta)
            elif bad == "half-size":
                f = Frame(f.image[::2, ::2].copy(), f.stamp_ns, f.seq, right=f.right[::2, ::2].copy(), meta=f.meta)
            elif bad == "uint16":
                f = Frame(f.image.astype(np.uint16) * 256, f.stamp_ns, f.seq, right=f.right.astype(np.uint16) * 256,
                          meta=f.meta)
            else:
                p = Pose2(float("nan"), p.z, p.theta)
        results.append(stage.process(f, p))
        if i == 4:
            assert (stage.revision, stage.stats["frames"], len(stage.map)) == before
    r = results[4]
    assert not r.ok and r.kind == "line_map" and r.value["segments"] == before[2]
    says = {"no-right": "no right image", "half-size": "the image is 320x240, the camera calibration is for 640x480",
            "uint16": "the image is uint16", "nan-odometry": "odometry is not finite"}[bad]
    assert r.info["reason"].startswith("line map: ") and says in r.info["reason"]
    assert stage.stats["unusable"] == 1 and stage.unusable_reason in r.info["reason"]
    assert all(e.ok for i, e in enumerate(results) if i != 4)
    assert stage.stats["frames"] == 7 and results[-1].info["fused"] > 0


def test_line_map_stage_takes_a_grey_plane_like_the_other_stages():
    """An HxWx1 grey pair (as some V4L2 cameras deliver, and as teach, repeat and the VSLAM take: frame_input.py)
    raised cv2.error in the line detector, which ends the run. The line map takes it as the grey image: the
    same map as from the HxW pair."""
    from vbnav.control.stages.line_map import LineMapStage
    from vbnav.drivers.camera import Frame

    poses = loop_poses(60)[:4]
    drive = render_drive(World.room(seed=1), poses)
    maps = []
    for plane in (False, True):
        stage = LineMapStage(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT,
                             abstraction_period_s=None)
        for f, p in zip(drive.frames, poses):
            if plane:
                f = Frame(f.image[:, :, None], f.stamp_ns, f.seq, right=f.right[:, :, None], meta=f.meta)
            assert stage.process(f, p).ok
        # The keyframes keep the left image's grey plane, for the top and lower edges' ridges.
        assert stage.map.keyframes and all(kf.image.shape == (CAM.height, CAM.width) for kf in stage.map.keyframes)
        maps.append(stage.map.P.copy())
    np.testing.assert_array_equal(maps[0], maps[1])


def test_the_line_map_refuses_a_distorted_camera():
    """LineMapStage.from_config took fx, fy, cx, cy alone: camera.distortion (or a fisheye model) was accepted
    and the distorted pair triangulated as if rectified. It is refused, naming the field."""
    from vbnav.control.config import parse_config
    from vbnav.control.stages.line_map import LineMapStage
    cfg = parse_config({"camera": {"options": {"stereo_baseline": 0.1}, "distortion": [-0.2, 0.05, 0, 0, 0]}})
    with pytest.raises(ValueError, match=r"rectified stereo pair .*camera.distortion \[-0.2, 0.05"):
        LineMapStage.from_config(cfg)
    LineMapStage.from_config(parse_config({"camera": {"options": {"stereo_baseline": 0.1}}}))


@pytest.mark.parametrize("config,driver", [("sentry-dynamixel", "v4l2"), ("sentry-oak", "oak")])
def test_the_line_map_refuses_a_camera_without_a_right_image(tmp_path, capsys, config, driver):
    """A V4L2 or OAK camera with a stereo calibration file (a baseline) was taken by the line map, whose every
    frame then lacked its right image and was skipped as unusable: `map build` drove its whole script to save an
    empty map, `goto --map` re-planned on a map that never grew. Both are refused before any device opens,
    naming the camera; `goto --map` without `--map-out` plans once from the file, and says so. An OAK gives its
    rectified pair with camera.options.right_image (tests/test_oak_camera.py), which the line map takes."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR
    data = yaml.safe_load((CONFIG_DIR / f"{config}.yaml").read_text())
    w, h = data["camera"]["width"], data["camera"]["height"]
    (tmp_path / "rig.yaml").write_text(f"width: {w}\nheight: {h}\nfx: 400\nfy: 400\ncx: {w / 2}\ncy: {h / 2}\n"
                                       "baseline: 0.075\n")
    data["camera"]["calibration_file"] = "rig.yaml"
    data["controller"] = {"kind": "scripted"}
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(data))
    said = f"both images of a stereo pair, and camera.driver {driver} gives one image per frame, no right image"
    assert main(["map", "build", "-c", str(tmp_path / "robot.yaml"), "--out", str(tmp_path / "m.json")]) == 2
    assert said in capsys.readouterr().err
    save_map(LineMap(), tmp_path / "room.json")
    assert main(["goto", "-c", str(tmp_path / "robot.yaml"), "--map", str(tmp_path / "room.json"), "--map-out",
                 str(tmp_path / "grown.json"), "--goal", "0", "1", "0"]) == 2
    out = capsys.readouterr()
    assert "--map-out" in out.err and said in out.err and "planning once" in out.out, out
    assert not (tmp_path / "m.json").exists() and not (tmp_path / "grown.json").exists()
    if driver == "oak":       # its rectified pair (camera.options.right_image): the line map takes it
        from vbnav.control.config import load_config
        from vbnav.control.stages.line_map import LineMapStage
        assert "camera.options.right_image: true" in out.err
        data["camera"]["options"]["right_image"] = True
        (tmp_path / "robot.yaml").write_text(yaml.safe_dump(data))
        assert LineMapStage.from_config(load_config(str(tmp_path / "robot.yaml"))).baseline == 0.075


@pytest.mark.parametrize("why", ["no-baseline", "distorted"])
def test_goto_localise_refused_says_what_to_do_for_its_reason(tmp_path, capsys, why):
    """`goto --localise` refused for a camera it cannot localise with (no stereo baseline) said "the map does not
    confirm a start pose ...: give --start nearer the robot's pose", advice that cannot help; a distorted camera
    was localised as if rectified. Each is refused before any device opens, naming the field and what to do."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR
    path = tmp_path / "room.json"
    save_map(LineMap(), path)
    cfg = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    if why == "no-baseline":
        cfg["camera"]["options"].pop("stereo_baseline", None)
        cfg.setdefault("vslam", {})["metric_scale"] = "odometry"
    else:
        cfg["camera"]["distortion"] = [0.1, 0.0, 0.0, 0.0, 0.0]
    cfg.setdefault("obstacles", {})["enabled"] = False     # it refuses a single camera and distortion too, for itself
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    args = ["goto", "-c", str(tmp_path / "robot.yaml"), "--map", str(path), "--static-map", "--localise",
            "--goal", "0", "1", "0", "--duration", "0.2"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--start nearer" not in err and "does not confirm a start pose" not in err, err
    if why == "no-baseline":
        assert "stereo_baseline" in err and "calibration_file" in err, err
    else:
        assert "camera.distortion" in err and "rectified" in err, err
    assert "leave out --localise" in err, err


def _refuse_to_save(monkeypatch, out):
    """save_map's load-back check refuses ``out`` (a map load_map would refuse), every other file loads."""
    from vbnav.control import line_map_file
    check = line_map_file.map_from_data

    def refuse(path, data):
        if Path(path) == Path(out):
            raise MapFileError(f"{path}: segments[0]: p0 and p1 are the same point")
        return check(path, data)
    monkeypatch.setattr(line_map_file, "map_from_data", refuse)


def test_a_map_build_whose_map_is_refused_still_prints_its_summary(tmp_path, monkeypatch, capsys):
    """A map save_map refused (it could not be loaded back) ended map build with exit 2 and the error alone: the
    run's summary (frames, segments, how it ended) was lost. It is printed, says the map was not saved, and the
    exit is the job's failure (1)."""
    from vbnav.control.cli import main
    out = tmp_path / "m.json"
    _refuse_to_save(monkeypatch, out)
    assert main(["map", "build", "-c", "sim_stereo", "--out", str(out), "--duration", "0.4"]) == 1
    captured = capsys.readouterr()
    assert "map build ended: duration" in captured.out and "verified segments" in captured.out, captured
    assert f"NOT SAVED to {out}" in captured.out, captured.out
    assert f"{out}: not saved, it could not be loaded back" in captured.err, captured.err
    assert not out.exists()


def test_map_build_on_the_simulated_clock_runs_the_slow_loop_on_simulated_time(tmp_path, monkeypatch):
    """On the simulated clock (faster than real time) map build ran the abstraction in a thread woken every
    second of wall time: how many passes the map got, and after which frames its hypotheses came, depended
    on the machine's load. Now it runs inline on the frames' simulated time, every ``period_s`` (15 frames
    at 15 Hz), and no thread starts."""
    from vbnav.control.cli import main
    from vbnav.control.stages import line_map as stage_module
    passes, threads, stages = [], [], []
    step, from_config = stage_module.AbstractionThread.step, stage_module.LineMapStage.from_config

    def counted(self):
        passes.append(stages[0].stats["frames"])      # the frames mapped when the pass ran
        return step(self)

    def built(cfg, **kw):
        stages.append(from_config(cfg, **kw))
        return stages[-1]

    monkeypatch.setattr(stage_module.LineMapStage, "from_config", built)
    monkeypatch.setattr(stage_module.AbstractionThread, "step", counted)
    monkeypatch.setattr(stage_module.AbstractionThread, "start", lambda self: threads.append(self))
    out = tmp_path / "m.json"
    assert main(["map", "build", "-c", "sim_stereo", "--out", str(out), "--duration", "2.5"]) == 0
    frames = json.loads(out.read_text())["meta"]["frames"]
    assert frames >= 36
    assert threads == []
    # 1 s and 2 s of simulated time after the first frame (frames 16 and 31 at 15 Hz), then the final pass.
    assert passes == [16, 31, frames]


def test_a_line_painted_on_a_face_belongs_to_no_edge():
    """The scorer's ``painted_lines``: a segment along an edge of a face's texture (a grey step 6 cm from
    the face's side) is a painted line, correct map content and the map of no edge; the face's own side
    (its border), a segment off the face's plane, and one across uniform texture are not."""
    from line_scenes import painted_lines
    world = World(seed=0)
    tex = np.full((256, 256), 60, np.uint8)                 # a 1 m x 1 m face at 256 texels per metre
    tex[:, 15:] = 180                                       # the step at a = 15 / 256 m = 5.9 cm
    tex.flags.writeable = False
    world.add_quad("face", "box", origin=[0.0, -1.0, 2.0], u=[1.0, 0.0, 0.0], v=[0.0, 1.0, 0.0],
                   width=1.0, height=1.0, texture=tex)
    x = 15 / 256
    segs = np.array([[[x, -0.8, 2.0], [x, -0.3, 2.0]],                # along the step
                     [[0.0, -0.8, 2.0], [0.0, -0.3, 2.0]],            # the face's side
                     [[x, -0.8, 2.1], [x, -0.3, 2.1]],                # 10 cm off the plane
                     [[0.5, -0.8, 2.0], [0.5, -0.3, 2.0]]])           # across uniform grey
    assert painted_lines(segs, world).tolist() == [True, False, False, False]
