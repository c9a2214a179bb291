"""FrozenImageWatch: the same image while the wheels move is frozen; a still scene, or a driver that
refills one buffer, is not."""
import numpy as np

from vbnav.control.runtime.frozen_image import MIN_TRAVEL_M, MIN_TURN_RAD, RECENT_IMAGES, FrozenImageWatch
from vbnav.vision.geometry import Pose2


def image(seed):
    return np.random.default_rng(seed).integers(0, 256, (48, 64, 3), dtype=np.uint8)


def test_same_image_is_fresh_until_the_robot_moves():
    w = FrozenImageWatch()
    img = image(0)
    assert w.fresh(img, Pose2())
    assert w.fresh(img.copy(), Pose2(0.0, 0.5 * MIN_TRAVEL_M, 0.5 * MIN_TURN_RAD))   # still, or nearly
    assert not w.frozen
    assert not w.fresh(img.copy(), Pose2(0.0, MIN_TRAVEL_M * 1.01, 0.0))              # drove 2 cm
    assert w.frozen
    assert w.fresh(image(1), Pose2(0.0, 0.1, 0.0))                                    # a new image
    assert not w.frozen


def test_a_turn_on_the_spot_freezes_it():
    w = FrozenImageWatch()
    img = image(0)
    assert w.fresh(img, Pose2(1.0, 2.0, 3.0))
    assert not w.fresh(img, Pose2(1.0, 2.0, 3.0 + 1.01 * MIN_TURN_RAD))
    # Travel counts from where the image last changed, not from the previous frame.
    w = FrozenImageWatch()
    assert w.fresh(img, Pose2())
    for k in range(1, 10):
        fresh = w.fresh(img, Pose2(0.0, k * 0.3 * MIN_TRAVEL_M, 0.0))
        assert fresh == (k * 0.3 < 1.0), k


def test_a_driver_that_refills_one_buffer():
    """Comparing the new frame with a kept reference to the same buffer would call every frame frozen."""
    w = FrozenImageWatch()
    buf = image(0)
    assert w.fresh(buf, Pose2())
    for k in range(1, 5):
        buf[...] = image(k)
        assert w.fresh(buf, Pose2(0.0, 0.1 * k, 0.0)), k
    assert not w.fresh(buf, Pose2(0.0, 1.0, 0.0))           # not refilled: frozen


def test_size_or_type_change_is_a_new_image():
    w = FrozenImageWatch()
    assert w.fresh(np.zeros((4, 4), np.uint8), Pose2())
    assert w.fresh(np.zeros((4, 5), np.uint8), Pose2(0.0, 1.0, 0.0))
    assert w.fresh(np.zeros((4, 5), np.uint16), Pose2(0.0, 2.0, 0.0))
    assert not w.fresh(np.zeros((4, 5), np.uint16), Pose2(0.0, 3.0, 0.0))


def test_frozen_frames_do_not_reach_the_stages():
    """A frozen frame pairs an old image with new odometry: fed to teach it would pull the landmarks'
    heights towards 'far' (no parallax while the wheels moved) and could start a keyframe whose image
    is not at its pose; fed to VSLAM, a pose that stops while the robot drives. The stages skip it (their
    estimates age, and the stale-camera stop comes camera.stale_after_s after the last fresh frame)."""
    from vbnav.control.controllers.manual import ScriptedController
    from vbnav.control.runtime.interfaces import Estimate, VisionStage
    from runtime_helpers import make_runtime

    class Seen(VisionStage):
        kind = "seen"

        def __init__(self):
            self.stamps = []

        def process(self, frame, odom):
            self.stamps.append(frame.stamp_ns)
            return Estimate(frame.stamp_ns, self.kind, True, None, {})

    t0 = 1_000_000_000                                   # SimClock start
    freeze, thaw = t0 + 1_000_000_000, t0 + 2_000_000_000
    stage = Seen()
    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 3.0]]), stages=[stage],
                                    cam_kw={"freeze_at_ns": freeze, "thaw_at_ns": thaw})
    rt.run()
    seen = np.array(stage.stamps)
    frame_ns = 1e9 / 15
    travel_ns = 0.02 / 0.3 * 1e9           # until the wheels have moved 2 cm, the same image is a still scene
    assert len(seen[seen < freeze]) >= 14 and len(seen[seen >= thaw]) >= 14
    inside = seen[(seen >= freeze) & (seen < thaw)]
    assert len(inside) <= 2 and np.all(inside <= freeze + travel_ns + frame_ns), (inside - freeze) / 1e6


def test_a_driver_that_cycles_its_last_buffers_is_frozen():
    """A hung V4L2 driver re-queues the buffers it holds (OpenCV's backend queues 4), so the frames cycle
    A, B, C, D, A, ...: each differs from the one before, and comparing with the last image only called
    them fresh for ever while the robot drove. An image seen among the last ``RECENT_IMAGES`` counts as
    the same image, frozen once the wheels moved since it was first seen."""
    for n in (2, RECENT_IMAGES):
        w = FrozenImageWatch()
        bufs = [image(k) for k in range(n)]
        fresh = [w.fresh(bufs[k % n].copy(), Pose2(0.0, 0.004 * k, 0.0)) for k in range(4 * n)]
        assert all(fresh[:n]), (n, fresh)              # each buffer is a new image the first time
        assert not any(fresh[-n:]), (n, fresh)         # driven 4 cm and more since: frozen
        assert w.frozen
        assert w.fresh(image(99), Pose2(0.0, 1.0, 0.0)) and not w.frozen   # a new image thaws it


def test_a_still_robot_among_recent_images_is_not_frozen():
    """The same few images while the wheels stand still (a noise-free scene flickering between two renders)
    stay fresh."""
    w = FrozenImageWatch()
    a, b = image(0), image(1)
    assert all(w.fresh(x.copy(), Pose2()) for x in (a, b, a, b, a, b))
    assert not w.frozen


def test_the_thresholds_follow_the_configured_cameras_focal_length():
    """The travel and turn that make an unchanged image frozen were derived for f = 500 px whatever the camera:
    a wide lens (f = 250 px, where 2 cm of travel shifts the edge point by 0.5 px) was called frozen by a still
    scene, a long one (f = 1000 px) was let run twice as far frozen. The pipeline's watch now takes the
    configured camera's fx: 1 px at the edge 5 m away, 2.5 px of turn."""
    from vbnav.control.config import parse_config
    from vbnav.control.runtime.factory import make_pipeline
    from vbnav.drivers.clock import SimClock

    for fx, travel, turn in ((250.0, 0.04, 0.01), (500.0, 0.02, 0.005), (1000.0, 0.01, 0.0025)):
        cfg = parse_config({"camera": {"fx": fx, "fy": fx}})
        w = make_pipeline(cfg, SimClock(), None, []).frozen
        img = image(0)
        assert w.fresh(img, Pose2())
        assert w.fresh(img, Pose2(0.0, 0.99 * travel, 0.99 * turn)), fx          # below both: still fresh
        assert not w.fresh(img, Pose2(0.0, 1.01 * travel, 0.0)), fx              # drove far enough: frozen
        assert w.fresh(image(1), Pose2()) and not w.fresh(image(1), Pose2(0.0, 0.0, 1.01 * turn)), fx
