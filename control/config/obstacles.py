"""The ``obstacles:`` section: ground-plane suppression and the stop/slow zones."""
from __future__ import annotations

import math
from typing import Literal, Optional

from pydantic import Field, model_validator
from vbnav.control.config.base import Strict, written


class ZoneConfig(Strict):
    name: str = Field(..., description="zone name, reported in the stage's estimates")
    action: Literal["stop", "slow"] = Field("stop", description="stop: the robot stops while the zone triggers; "
                                                                "slow: speeds are scaled by slow_scale")
    distance: Optional[float] = Field(None, gt=0, description="band: length ahead of the axle centre, m "
                                                               "(give distance and half_width, or polygon)")
    half_width: Optional[float] = Field(None, gt=0, description="band: width either side of the centre line, m")
    polygon: Optional[list[tuple[float, float]]] = Field(None, description="instead of a band: at least 3 "
                                                                           "(x right, z forward) vertices, m")
    slow_scale: float = Field(0.4, ge=0, le=1, description="speed factor while a slow zone triggers (slow zones "
                                                           "only: refused on a stop zone)")
    min_points: int = Field(8, ge=1, description="obstacle pixels inside that trigger the zone")
    min_distance: Optional[float] = Field(
        None, gt=0, description="stop bands only: m ahead of the axle centre where the robot stands still; with it "
                                "the band is a protective field whose length follows the speed (an obstacle at d "
                                "in the band scales the speed by (d - min_distance) / (distance - min_distance), "
                                "0 at min_distance: a held stop; refused nearer than where the camera's view of the "
                                "floor under the band begins); without it any obstacle in the band stops the "
                                "robot (docs/obstacles.md, 'A stop band that follows the speed')")

    @model_validator(mode="after")
    def _shape(self):
        band = self.distance is not None or self.half_width is not None
        if band and self.polygon is not None:
            raise ValueError(f"zone {self.name!r}: give either distance/half_width (a band) or polygon, not both")
        if self.polygon is None and (self.distance is None or self.half_width is None):
            raise ValueError(f"zone {self.name!r}: a band needs both distance and half_width (or give polygon)")
        if self.polygon is not None and len(self.polygon) < 3:
            raise ValueError(f"zone {self.name!r}: polygon needs at least 3 vertices")
        if self.polygon is not None and not all(math.isfinite(v) for vertex in self.polygon for v in vertex):
            raise ValueError(f"zone {self.name!r}: polygon vertices must be finite numbers, m")
        if self.min_distance is not None:
            if self.action != "stop" or self.polygon is not None:
                raise ValueError(f"zone {self.name!r}: min_distance {self.min_distance:g} shortens a stop band "
                                 f"with the speed, and this zone is {'a polygon' if self.polygon is not None else 'a slow zone'}; "
                                 f"use it on a band (distance, half_width) with action: stop, or remove it")
            if not self.min_distance < self.distance:
                raise ValueError(f"zone {self.name!r}: min_distance {self.min_distance:g} m must be shorter than the "
                                 f"band's distance {self.distance:g} m (its length at full speed)")
        if self.action == "stop" and written(self, "slow_scale"):
            raise ValueError(f"zone {self.name!r}: slow_scale {self.slow_scale:g} is the speed factor of a slow "
                             f"zone, and this zone has action: stop (it stops the robot); set action: slow, or "
                             f"remove slow_scale")
        return self



def _default_zones() -> list[ZoneConfig]:
    return [ZoneConfig(name="stop", action="stop", distance=0.8, half_width=0.25),
            ZoneConfig(name="slow", action="slow", distance=1.5, half_width=0.35, slow_scale=0.4)]



#: The settings of the piecewise ground model, unread by ``ground_model: plane``.
PIECEWISE_GROUND_KEYS = ("ground_band_ratio", "ground_corridor_half_width", "max_grade_change", "cross_slope_allowance")


class ObstaclesConfig(Strict):
    enabled: bool = Field(False, description="run the obstacle stage (needs a stereo camera: refused at load for "
                                               "one whose frames carry neither a disparity nor a right image)")
    source: Literal["auto", "disparity", "sgbm"] = Field(
        "auto", description="disparity: the frames' own (OAK); sgbm: computed from the stereo pair (refused for a "
                            "camera whose frames have no right image); auto: the frames' own if present, else sgbm")
    baseline: Optional[float] = Field(None, gt=0, description="m; default the camera's stereo baseline "
                                      "(camera.calibration_file's, else camera.options.stereo_baseline), else the "
                                      "frames' meta['baseline_m'] (OAK); given with a calibration file that has "
                                      "one, or with camera.options.stereo_baseline, the two must agree within 1 %")
    obstacle_height: float = Field(0.02, gt=0, description="m above the floor that is an obstacle")
    negative_depth: float = Field(0.03, gt=0, description="m below the floor that is a negative obstacle")
    noise_px: float = Field(0.4, ge=0, description="disparity noise floor, px")
    max_height: Optional[float] = Field(1.0, gt=0, description="m; higher points are overhangs, ignored")
    max_range: float = Field(6.0, gt=0, description="m; farther points are ignored")
    min_blob_pixels: int = Field(12, ge=1, description="smaller connected obstacle regions are matching "
                                                     "noise, px")
    negative_stops: bool = Field(True, description="negative obstacles (steps down) trigger zones too")
    fit_inlier_height: float = Field(0.02, gt=0, description="m, ground-plane fit inlier band")
    ground_model: Literal["piecewise", "plane"] = Field(
        "piecewise", description="piecewise: near band fitted under the mounting's bounds, farther bands hinged "
                                 "(kerbs, camber, ramps; docs/obstacles.md); plane: one plane for the whole floor")
    mount_height_tol: float = Field(0.05, gt=0, description="m: a near-band fit whose camera height is further "
                                    "than this from camera.mount.height is rejected")
    mount_tilt_tol_deg: float = Field(2.0, gt=0, le=30, description="deg: a near-band fit whose pitch or roll is "
                                      "further than this from the mounting's is rejected")
    ground_corridor_half_width: float = Field(1.0, gt=0, description="m either side of the camera's line ahead "
                                              "where the ground is fitted (piecewise ground only: refused "
                                              "with ground_model plane)")
    ground_band_ratio: float = Field(1.414, gt=1.05, le=4, description="far / near distance of one ground band "
                                     "(piecewise ground only: refused with ground_model plane)")
    max_grade_change: float = Field(0.08, ge=0, le=0.5, description="rise over run a band may bend by from the "
                                    "one before (a ramp; piecewise ground only: refused with ground_model plane)")
    cross_slope_allowance: float = Field(0.06, ge=0, le=0.5, description="beyond the corridor the thresholds grow "
                                         "by this much per metre (camber; piecewise ground only: refused with "
                                         "ground_model plane)")
    sgbm_block_size: int = Field(3, ge=1, le=11, description="SGBM matching block side, px, odd; SGBM runs with "
                                 "source sgbm, or auto on frames with a right image and no disparity (written with "
                                 "source disparity, or auto on the simulated camera or an OAK, which give their "
                                 "own: refused)")
    persist_k: int = Field(2, ge=1, description="a zone must trigger in k of the last n frames")
    persist_n: int = Field(3, ge=1, description="n of k-of-n (n >= persist_k)")
    release_s: float = Field(0.5, ge=0, description="clear this long before the speed rises again")
    turn_when_held: bool = Field(False, description="while an obstacle seen in a stop zone holds the robot, let "
                                 "the controller turn on the spot (forward speed held at 0; the drive stays "
                                 "enabled): a round robot (robot.footprint_radius, refused without it) sweeps no "
                                 "floor outside its footprint, and a goal or route that turns away from the obstacle "
                                 "is no longer a deadlock; a blind or stale stage still stops both")
    zones: list[ZoneConfig] = Field(default_factory=_default_zones, description="stop and slow zones on the "
                                    "floor, in the robot frame")
    sgbm_near_margin: float = Field(0.85, gt=0, le=1, description="stereo matching covers depths down to this "
                                    "share of the distance to the nearest floor point in view: a 15 % margin, "
                                    "so an obstacle standing there is still matched")

    @model_validator(mode="after")
    def _k_le_n(self):
        if self.persist_k > self.persist_n:
            raise ValueError(f"persist_k ({self.persist_k}) must be <= persist_n ({self.persist_n})")
        if self.sgbm_block_size % 2 == 0:
            raise ValueError(f"sgbm_block_size must be odd, got {self.sgbm_block_size}")
        unused = [k for k in ("sgbm_block_size", "sgbm_near_margin") if written(self, k)]
        if self.source == "disparity" and unused:
            raise ValueError(f"{' and '.join(unused)} {'set' if len(unused) > 1 else 'sets'} the stereo matching "
                             f"(SGBM), which source: disparity never "
                             f"runs (it takes the frames' own disparity); remove {' and '.join(unused)}, or set "
                             f"source: auto or sgbm")
        # the piecewise ground's shape (control/stages/obstacles.py ground_model_params: None for one plane); the
        # words of 'vbnav obstacles' refusing its --ground-half-width etc. with --ground plane
        flat = [k for k in PIECEWISE_GROUND_KEYS if written(self, k)]
        if self.ground_model == "plane" and flat:
            raise ValueError(f"{' and '.join(flat)}: {'shape' if len(flat) > 1 else 'shapes'} the piecewise ground; "
                             f"ground_model: plane fits one plane, which never reads "
                             f"{'them' if len(flat) > 1 else 'it'} (remove {' and '.join(flat)}, or set "
                             f"ground_model: piecewise)")
        if not self.zones:
            raise ValueError("zones: at least one zone (the stage watches the floor of the stop zones; without "
                             "zones it could never slow or stop the robot)")
        names = [z.name for z in self.zones]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            # Each zone's k-of-n persistence is kept by its name: two zones of one name would share it,
            # and a slow zone could clear a stop zone's history.
            raise ValueError(f"zones: names must be unique (each keeps its own trigger history), "
                             f"{', '.join(map(repr, twice))} given more than once")
        return self
