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
