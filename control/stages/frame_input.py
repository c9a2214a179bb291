"""Where a frame enters a feature-tracking stage (teach, repeat, VSLAM, line map): its image as the stage
takes it (HxW grey uint8 of the configured camera's size), or why this frame cannot be used.

A frame the stage cannot use is not a fault of the run: the stage returns an estimate that is not ok
with the reason in ``info['reason']``, keeps its state from the last good frame and goes on with the
next frame (a camera renegotiating its size after a reconnect delivers good frames again later).

- Colour (HxWx3 BGR, HxWx4 BGRA, as the sim, V4L2 and replay drivers give with ``grey: false``) is made
  grey the way the stages always did (``vision.features.to_grey``); HxWx1 is the grey plane.
- Another size than the camera's: the intrinsics (and a route's keyframes) are for one size, so the
  frame is refused naming both sizes; no resize, which would silently need another calibration.
- Another dtype than uint8 (a 16-bit or float stream): refused naming the dtype. There is no clearly
  right conversion (a 16-bit image may hold 10, 12 or 16 significant bits, a float one 0-1 or 0-255).
  The obstacle stage refuses such a stereo pair the same way (``dtype_problem``): each image stretched
  to 8 bits on its own, a highlight in one of them or a NaN pixel left SGBM matching two different
  exposures, blind for the wrong reason or slowed for an obstacle that is not there.

The frame's odometry (``odometry_problem``) is checked the same way: a pose with a NaN or infinite
coordinate (a drive reporting a NaN encoder position) cannot place the frame, and a fix or keyframe
taken at it would carry the NaN into the controllers and the route.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from vbnav.drivers.calibration import CalibrationError, check_baseline
from vbnav.vision.features import to_grey


def dtype_problem(image: np.ndarray, what: str = "image") -> str:
    """"" when ``image`` is 8-bit (uint8), else why a stage does not take it (naming its dtype)."""
    if image.dtype != np.uint8:
        return f"the {what} is {image.dtype}, the stage takes 8-bit (uint8) images"
    return ""


def stage_image(image: Optional[np.ndarray], camera, what: str = "image") -> tuple[Optional[np.ndarray], str]:
    """(grey uint8 image, "") when ``image`` is usable with ``camera`` (its ``width`` x ``height``),
    else (None, the reason). ``what`` names the image in the reason ("image", "right image")."""
    if image is None:
        return None, f"the frame has no {what}"
    image = np.asarray(image)
    why = dtype_problem(image, what)
    if why:
        return None, why
    if image.ndim == 3 and image.shape[2] == 1:
        image = np.ascontiguousarray(image[:, :, 0])
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        image = to_grey(image)
    elif image.ndim != 2:
        return None, (f"the {what} has shape {tuple(image.shape)}, the stage takes HxW grey or HxWx3 BGR "
                      "images")
    h, w = image.shape
    if (w, h) != (int(camera.width), int(camera.height)):
        return None, (f"the {what} is {w}x{h}, the camera calibration is for {int(camera.width)}x"
                      f"{int(camera.height)}")
    return image, ""


def disparity_problem(disparity: np.ndarray, camera) -> str:
    """"" when ``disparity`` is a disparity image the stages take: floats in pixels (NaN unknown) of the
    camera's ``width`` x ``height``; else why not. An integer one is a raw device format whose scale is not
    known here (an OAK's has 3 subpixel bits): taken as pixels, every depth is that many times too near."""
    d = np.asarray(disparity)
    if not np.issubdtype(d.dtype, np.floating):
        return f"the disparity image is {d.dtype}, the stage takes disparity in pixels as floats (NaN unknown)"
    w, h = int(camera.width), int(camera.height)
    if d.shape != (h, w):
        size = f"{d.shape[1]}x{d.shape[0]}" if d.ndim == 2 else f"of shape {tuple(d.shape)}"
        return f"the disparity image is {size}, the camera calibration is for {w}x{h}"
    return ""


def frame_baseline(frame) -> tuple[Optional[float], str]:
    """(baseline m, "") from the frame's ``meta['baseline_m']`` (a camera reporting its device's stereo
    calibration, the OAK) when it is a finite distance > 0, else (None, why): a camera that sends none, or
    a calibration gone wrong (NaN, inf, <= 0, not a number) is a frame the stage cannot use."""
    b = (frame.meta or {}).get("baseline_m")
    if b is None:
        return None, "the frame carries no meta['baseline_m']"
    try:
        return check_baseline("the frame", b, "meta['baseline_m']"), ""
    except CalibrationError:
        return None, f"the frame's meta['baseline_m'] is {b!r}, not a distance > 0"


def odometry_problem(odom) -> str:
    """"" when the odometry pose of a frame is finite, else why the frame cannot be used with it."""
    values = (odom.x, odom.z, odom.theta)
    if all(math.isfinite(v) for v in values):
        return ""
    return (f"the odometry is not finite (x {values[0]}, z {values[1]}, theta {values[2]}): the frame cannot "
            "be placed")
