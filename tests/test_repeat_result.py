"""What a repeat says it reached (control/session.py RepeatResult)."""
from __future__ import annotations

from vbnav.control.session import RepeatResult


def _result(completed: bool, heading_for: int) -> RepeatResult:
    return RepeatResult(completed, "finished" if completed else "blind", "", heading_for, 10, [], None, 0)


def test_a_repeat_stopped_on_the_way_says_the_keyframes_it_passed_not_the_one_it_was_heading_for():
    """Found by the messages audit: 'reached keyframe N of M' printed the index of the keyframe the robot was
    heading for plus one, one more than it had reached."""
    stopped = _result(False, 3)
    assert stopped.keyframes_passed == 3
    assert stopped.progress_text() == "passed 3 of 10 keyframes (heading for keyframe 4)"
    done = _result(True, 9)
    assert done.keyframes_passed == 10 and done.progress_text() == "reached keyframe 10 of 10"


def test_the_start_up_wait_for_a_first_frame_is_no_stop_on_the_way():
    """Found by the messages audit: a repeat's 'safety holds on the way' (the demo's safety_stops) counted every
    hold, the camera_waiting every run has at start-up included: an idle 0.3 s run had one."""
    from vbnav.control.config import load_config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.runtime import Runtime
    cfg = load_config(None)
    robot = make_robot(cfg, with_camera=True)
    result = Runtime(cfg, robot.drive, IdleController(), robot.clock, robot.pipeline).run(0.3)
    assert result.count("hold", "camera_waiting") == 1
    assert result.holds_on_the_way() == 0
