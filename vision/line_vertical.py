"""Vertical 3D lines found along the pencil through the vertical vanishing point (issue 16).

A box corner in front of a textured wall is an occluding boundary: the wall behind it crosses the box
face's grey every few tens of rows, so the contrast across the edge changes sign there and LSD keeps
short pieces of it (or none far away). A ground robot knows which way is up (the mount and the pose), so
every vertical 3D line passes through the vertical vanishing point in the image; for a level camera that
is at infinity along the columns. Along each line of that pencil the gradient across it is looked at in
MAGNITUDE (either sign), so a sign change breaks the edge only over the Sobel's 3 rows.

Per image (``pencil_runs``):

1. the image is resampled so that the pencil's lines are its columns, rows kept (``pencil_map``;
   the identity for a level camera; a rectified pair's rows stay rows, so one resampling serves both);
2. ``M`` = |3x3 Sobel across the columns| / 8; the image noise sigma is estimated from the median
   absolute Laplacian-like residual (Immerkaer's mask, robust to edges; the left image's, once per pair),
   and the Sobel's noise is sigma x sqrt(12) / 8; a pixel supports a column when it is a local maximum of
   ``M`` along its row, above ``vertical_k_sigma`` of that noise, with a gradient pointing across the
   columns (within 45 deg; also halves the work on texture), with its parabola-interpolated position
   within ``vertical_tol_px`` of the column (a 1-D Hough over the pencil, two bins per ridge at most);
3. along each column, supported rows with gaps of at most ``vertical_gap_px`` (a contrast sign change
   leaves the Sobel's 3 rows and the ridge's own row weak; a closing, so rounded up to even) form runs;
   a run at least ``min_length_px`` long with at least half its rows supported, whose ridges' fitted line
   stays vertical within 3 sigma of its slope (``sigma_perp_px`` per ridge), is a line; its sub-pixel
   column is the magnitude-weighted mean of its ridges' positions (the least-squares line with the
   direction fixed by the vanishing point); of two runs within a pixel of each other on overlapping rows
   the stronger is kept; a run that is one step of a slanted LSD segment is dropped (``slanted``).

Matching (``match_vertical``): a left and a right run on the same rows (overlap >= ``min_overlap`` of the
shorter) with a disparity in range are a candidate when one side band (``band_px`` off the line) matches
between the images (mean |left - right| <= ``band_max_diff``: the near surface, which owns the
boundary, is the same in both; the edge search's test), better there than a pixel to either side (at a
wrong disparity the match is another structure's) and 2x better than 3 px to either side (the floor
test's rule: a weakly textured side proves nothing), while the other side does not match (an
occluding boundary: the background behind it shifts by another disparity; a line whose both sides match
lies on a surface, where its contrast does not change sign and LSD has it). A plain near side (an
untextured face) matches as well at any disparity near the line's, so it cannot pass that test: for a left
run without such a confirmed candidate, one whose near side matches at the noise's level (2 sigma /
sqrt(pi), the mean |l - r| of noise alone) is taken on the lines' positions, and of such candidates at
several disparities (the face's grey meets every background line ending on it) the one sharing 2x the
rows of each of the others. A left run with candidates at disparities more than a pixel apart (periodic texture)
gets none, and of candidates within a pixel of one disparity (the right image's run broken into pieces)
the one sharing most rows is kept. ``add_vertical_matches`` appends them to the pair's matches.
"""
from __future__ import annotations

import math
from typing import Optional

import cv2
import numpy as np

from vbnav.vision import line_vertical_kernel
from vbnav.vision.line_segments import LineParams, Segments2D, StereoMatches, _sample, _x_at, gradients, grey, side_means

SOBEL_NOISE_GAIN = math.sqrt(12.0) / 8.0      # 3x3 Sobel / 8 of iid noise: sigma x sqrt(1+4+1+1+4+1) / 8
PLAIN_NOISE_GAIN = 2.0 / math.sqrt(math.pi)   # E|n1 - n2| of two samples with iid noise sigma: 2 sigma / sqrt(pi)


def noise_sigma(image: np.ndarray) -> float:
    """Robust image noise sigma (Immerkaer's mask [1 -2 1; -2 4 -2; 1 -2 1], norm 6, whose response to
    planar intensity is zero; the median of its absolute response / 0.6745 ignores edges and texture)."""
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = cv2.filter2D(image.astype(np.float32), cv2.CV_32F, k)[1:-1:4, 1:-1:4]      # every 16th pixel: enough
    return float(np.median(np.abs(r)) / 0.6745 / 6.0)


def pencil_map(vertical: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """Maps (x, y) for ``cv2.remap`` that make the lines through the vertical vanishing point columns (rows
    kept), or None for a level camera. ``vertical``: the world's vertical in the camera frame.
    A pencil line with column c runs through (c, cy) and the vanishing point K v:
    x(y) = c (1 - (y - cy) vz / (fy vy)) + (y - cy) (fx vx + cx vz) / (fy vy)."""
    vx, vy, vz = (float(a) for a in vertical)
    if abs(vx) < 1e-9 * abs(vy) and abs(vz) < 1e-9 * abs(vy):
        return None
    c = np.arange(width, dtype=np.float32)[None, :]
    dy = (np.arange(height, dtype=np.float32) - cy)[:, None]
    mx = c * (1.0 - dy * vz / (fy * vy)) + dy * (fx * vx + cx * vz) / (fy * vy)
    my = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], mx.shape)
    return mx.astype(np.float32), np.ascontiguousarray(my, np.float32)


def pencil_runs(image: np.ndarray, params: LineParams = LineParams(), noise: Optional[float] = None,
                grad: Optional[tuple] = None) -> np.ndarray:
    """Runs along the columns of a (pencil-resampled) grey image: (K, 4) column (sub-pixel), first row,
    last row, strength (mean magnitude across the line over the supported rows). ``noise``: the image
    noise sigma (default: ``noise_sigma`` of this image); ``grad``: its ``gradients``, if the caller has them."""
    g = np.asarray(image, np.float32)
    gx, gy = gradients(g) if grad is None else grad
    M = np.abs(gx)
    thr = params.vertical_k_sigma * SOBEL_NOISE_GAIN * (noise_sigma(g) if noise is None else noise)
    if line_vertical_kernel.AVAILABLE:          # float32 as ``gradients`` gives them: one compiled signature
        runs = line_vertical_kernel.column_runs(np.ascontiguousarray(M, np.float32), np.ascontiguousarray(gy, np.float32),
                                                np.float32(thr), params.vertical_tol_px, int(params.vertical_gap_px),
                                                params.min_length_px, params.sigma_perp_px)
    else:
        runs = column_runs(M, gy, thr, params)
    return _strongest_of_neighbours(runs)


def column_runs(M: np.ndarray, gy: np.ndarray, thr: float, params: LineParams = LineParams()) -> np.ndarray:
    """The numpy reference of ``line_vertical_kernel.column_runs``: (K, 4) runs (column, first row, last
    row, strength) of |gradient across| ``M`` above ``thr``, sorted by column then row, before
    ``_strongest_of_neighbours``."""
    H, W = M.shape
    # Local maxima along the rows, above the noise, where the gradient points across the columns (within
    # 45 deg: the edge itself runs within 45 deg of the pencil's line).
    ridge = (M >= cv2.dilate(M, np.ones((1, 3), np.uint8))) & (M > thr)
    ridge &= np.abs(gy) < M
    ridge[:, :2] = ridge[:, -2:] = False                                         # the Sobel's border columns
    flat = np.flatnonzero(ridge)
    if len(flat) == 0:
        return np.zeros((0, 4))
    Mf = M.ravel()
    am, bm, cm = Mf[flat - 1], Mf[flat], Mf[flat + 1]
    curv = am - 2.0 * bm + cm
    o = np.where(curv < 0, 0.5 * (am - cm) / np.where(curv < 0, curv, -1.0), 0.0)     # sub-pixel offset
    # A ridge at column x + o supports each column within vertical_tol_px of it: x itself (|o| <= 0.5), and
    # x + 1 or x - 1 when o is within tol of it. Support S, weight (|gradient|) and weighted position sums
    # (a ridge's own column first, then its neighbours': each pixel holds one ridge, so the scatters below
    # add no index twice).
    tol = params.vertical_tol_px
    right, left = o >= 1.0 - tol, o <= tol - 1.0
    pos = (flat % W) + o
    bw = bm.astype(np.float64)
    S, Wt, Wp = np.zeros(H * W, np.uint8), np.zeros(H * W), np.zeros(H * W)
    S[flat], Wt[flat], Wp[flat] = 1, bw, bw * pos
    for side, step in ((right, 1), (left, -1)):
        k = flat[side] + step
        S[k] += 1
        Wt[k] += bw[side]
        Wp[k] += bw[side] * pos[side]
    S, Wt, Wp = S.reshape(H, W), Wt.reshape(H, W), Wp.reshape(H, W)
    # Runs: supported rows with gaps of at most vertical_gap_px (a morphological closing along the columns).
    gap = int(params.vertical_gap_px)
    B = (S > 0).astype(np.uint8)
    C = cv2.morphologyEx(B, cv2.MORPH_CLOSE, np.ones((2 * ((gap + 1) // 2) + 1, 1), np.uint8)) if gap > 0 else B
    L = int(math.ceil(params.min_length_px))
    long = cv2.erode(C, np.ones((2 * (L // 2) + 1, 1), np.uint8))                 # rows amid a run of >= L
    cand = np.nonzero(long.any(axis=0))[0]                                        # columns holding a run
    if len(cand) == 0:
        return np.zeros((0, 4))
    D = np.zeros((len(cand), H + 2), np.int8)                                     # the columns, padded
    D[:, 1:-1] = cv2.transpose(C)[cand]
    d = D[:, 1:] - D[:, :-1]                                                      # (cols, H + 1)
    k0, r0 = np.nonzero(d == 1)                                                  # sorted by column, then row
    _, r1 = np.nonzero(d == -1)
    r1 = r1 - 1
    keep = (r1 - r0 + 1) >= params.min_length_px
    cs, r0, r1 = cand[k0[keep]], r0[keep], r1[keep]
    if len(cs) == 0:
        return np.zeros((0, 4))
    cols, ci = np.unique(cs, return_inverse=True)
    rows = np.arange(H, dtype=np.float64)[:, None]
    Sc, Wc, Pc = S[:, cols].astype(np.float64), Wt[:, cols], Wp[:, cols]
    cum = np.zeros((H + 1, len(cols)))

    def span(img):                                   # sums over each run's rows [r0, r1]
        np.cumsum(img, axis=0, out=cum[1:])
        return cum[r1 + 1, ci] - cum[r0, ci]

    n, sw, swp = span(Sc), span(Wc), span(Pc)
    swr, swrr, swrp = span(Wc * rows), span(Wc * rows * rows), span(Pc * rows)
    length = r1 - r0 + 1
    ok = 2 * n >= length
    sw = np.maximum(sw, 1e-9)
    rbar, pbar = swr / sw, swp / sw
    # The ridges' weighted least-squares line p = a + b (row - mean row): a line of the pencil has b = 0
    # within its noise; a texture line a few degrees off vertical crosses the tolerance band in pieces.
    # Across the run the fitted line may move 3 sigma of its slope's estimate from n ridges of sigma_perp:
    # sigma_perp sqrt(12 / n) end to end.
    slope = (swrp - rbar * swp) / np.maximum(swrr - rbar * swr, 1e-9)
    ok &= np.abs(slope) * length <= 3.0 * params.sigma_perp_px * np.sqrt(12.0 / np.maximum(n, 1))
    if not ok.any():
        return np.zeros((0, 4))
    return np.column_stack((pbar, r0, r1, sw / np.maximum(n, 1)))[ok]


def _strongest_of_neighbours(runs: np.ndarray) -> np.ndarray:
    # Of two runs within a pixel on overlapping rows (a ridge supports two columns) keep the stronger.
    near = (np.abs(runs[:, None, 0] - runs[None, :, 0]) <= 1.0) & \
        (np.minimum(runs[:, None, 2], runs[None, :, 2]) >= np.maximum(runs[:, None, 1], runs[None, :, 1]))
    total = runs[:, 3] * (runs[:, 2] - runs[:, 1] + 1)
    idx = np.arange(len(runs))
    beaten = near & ((total[None, :] > total[:, None]) | ((total[None, :] == total[:, None]) & (idx[None, :] < idx[:, None])))
    return runs[~beaten.any(axis=1)]


def _to_image(runs: np.ndarray, maps) -> np.ndarray:
    """(K, 4) image segments x0, y0, x1, y1 (top to bottom) of runs in the resampled image."""
    y0, y1 = runs[:, 1], runs[:, 2]
    if maps is None:
        return np.column_stack((runs[:, 0], y0, runs[:, 0], y1))
    mx = maps[0]
    W = mx.shape[1]

    def x_of(c, y):
        yi = y.astype(int)
        c0 = np.clip(np.floor(c).astype(int), 0, W - 2)
        f = c - c0
        return mx[yi, c0] * (1 - f) + mx[yi, c0 + 1] * f

    return np.column_stack((x_of(runs[:, 0], y0), y0, x_of(runs[:, 0], y1), y1))


def vertical_lines(left_image: np.ndarray, right_image: np.ndarray, vertical: np.ndarray, fx: float, fy: float,
                   cx: float, cy: float, params: LineParams = LineParams(),
                   left_xy: Optional[np.ndarray] = None, grads: Optional[tuple] = None) -> tuple[np.ndarray, np.ndarray]:
    """Matched vertical lines of a rectified pair: left and right image segments (K, 4) on the same rows.
    ``left_xy``: the left image's LSD segments; a run that is a step of one of them is dropped (``slanted``).
    ``grads``: ``gradients`` of both images' grey levels, if the caller has them (used for a level camera,
    whose pencil is the columns: no resampling)."""
    L, R = grey(left_image).astype(np.float32), grey(right_image).astype(np.float32)
    H, W = L.shape
    maps = pencil_map(vertical, fx, fy, cx, cy, W, H)
    if maps is not None:
        grads = None                             # the resampled images' gradients are not the images'
        L = cv2.remap(L, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        R = cv2.remap(R, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    noise = noise_sigma(L)                       # one camera pair: one noise level
    lr = pencil_runs(L, params, noise, grads and grads[0])
    if left_xy is not None and len(lr) and len(left_xy):
        lr = lr[~slanted(_to_image(lr, maps), left_xy, params)]
    none = np.zeros((0, 4)), np.zeros((0, 4))
    if len(lr) == 0:                             # nothing to match: the right image's runs are not needed
        return none
    rr = pencil_runs(R, params, noise, grads and grads[1])
    if len(rr) == 0:
        return none
    li, ri, lo, hi = match_vertical(L, R, lr, rr, params, noise)
    if len(li) == 0:
        return none
    lseg = np.column_stack((lr[li, 0], lo, hi))
    rseg = np.column_stack((rr[ri, 0], lo, hi))
    lxy = _to_image(np.column_stack((lseg, np.zeros(len(li)))), maps)
    rxy = _to_image(np.column_stack((rseg, np.zeros(len(ri)))), maps)
    return lxy, rxy


def slanted(run_xy: np.ndarray, seg_xy: np.ndarray, params: LineParams = LineParams()) -> np.ndarray:
    """(K,) bool: runs that are one step of a longer slanted line. A line a few degrees off the pencil
    rendered (or sampled) in whole-pixel steps is a staircase of exactly vertical pieces, each as long as
    ``min_length_px`` when the slope is under 1 / 25; LSD (15 deg tolerance) sees the whole line. A run is a
    step when an LSD segment passes within 1 px of its middle and within its band (2 ``vertical_tol_px``)
    at its ends, shares at least half its rows, and leaves its line by more than 2 px (a staircase's step:
    more than the run's own band) within its own extent."""
    ym = 0.5 * (run_xy[:, 1] + run_xy[:, 3])                                     # (K,)
    xr = lambda y: _x_at(run_xy[:, None, :], y)                                   # noqa: E731
    xs = lambda y: _x_at(seg_xy[None, :, :], y)                                   # noqa: E731
    steep = np.abs(seg_xy[:, 3] - seg_xy[:, 1]) > np.abs(seg_xy[:, 2] - seg_xy[:, 0])
    through = np.abs(xs(ym[:, None]) - xr(ym[:, None])) <= 1.0                   # (K, S)
    for y in (run_xy[:, 1], run_xy[:, 3]):            # and stays in the run's band over the run's rows
        through &= np.abs(xs(y[:, None]) - xr(y[:, None])) <= 2.0 * params.vertical_tol_px
    lo = np.maximum(run_xy[:, None, 1], np.minimum(seg_xy[None, :, 1], seg_xy[None, :, 3]))
    hi = np.minimum(run_xy[:, None, 3], np.maximum(seg_xy[None, :, 1], seg_xy[None, :, 3]))
    shared = (hi - lo) >= 0.5 * (run_xy[:, None, 3] - run_xy[:, None, 1])
    leave = np.maximum(np.abs(xs(seg_xy[None, :, 1]) - xr(seg_xy[None, :, 1])),
                       np.abs(xs(seg_xy[None, :, 3]) - xr(seg_xy[None, :, 3]))) > 2.0
    return (steep[None, :] & through & shared & leave).any(axis=1)


def match_vertical(L: np.ndarray, R: np.ndarray, lr: np.ndarray, rr: np.ndarray,
                   params: LineParams = LineParams(), noise: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Indices (left run, right run) of the unique candidates (see the module docstring), in the resampled
    images (columns are the pencil's lines, so a column shift is the disparity up to the row's scale), and
    each one's first and last matched row. ``noise``: the images' noise sigma (``noise_sigma``), which says
    when a plain side matches; 0: no candidate on a plain side."""
    lo = np.maximum(lr[:, None, 1], rr[None, :, 1])
    hi = np.minimum(lr[:, None, 2], rr[None, :, 2])
    shorter = np.minimum(lr[:, None, 2] - lr[:, None, 1], rr[None, :, 2] - rr[None, :, 1])
    overlap = np.clip(hi - lo, 0, None) / np.maximum(shorter, 1e-9)
    disp = lr[:, None, 0] - rr[None, :, 0]
    cand = (overlap >= params.min_overlap) & (disp >= params.min_disparity_px) & (disp <= params.max_disparity_px)
    # Every band sample (up to 3 px of disparity shift beyond the outer band) inside both images.
    reach = max(params.band_px) + 4.0
    W = L.shape[1]
    cand &= (lr[:, None, 0] - reach >= 0) & (lr[:, None, 0] + reach <= W - 1) \
        & (rr[None, :, 0] - reach >= 0) & (rr[None, :, 0] + reach <= W - 1)
    a, b = np.nonzero(cand)
    if len(a) == 0:
        return a, b, np.zeros(0), np.zeros(0)
    k = params.edge_samples
    t = (np.arange(k) + 0.5) / k
    ys = lo[a, b][:, None] + (hi[a, b] - lo[a, b])[:, None] * t[None]               # (C, k)
    xl = np.broadcast_to(lr[a, 0][:, None], ys.shape)
    d = disp[a, b][:, None, None]
    off = np.asarray(params.band_px, float)[None, None, :]
    slants = band_slants(params)
    shifts = (-3.0, -1.0, 0.0, 1.0, 3.0)
    # cost[j, g, s, c]: side j (+1: right of the line, -1: left) of candidate c, its band sampled in the right
    # image at the disparity d + shift s + slant g x the band offset (the near surface is a plane through the
    # line, not fronto-parallel: a box face seen obliquely changes disparity by up to 2/3 px per px).
    cost = np.zeros((2, len(slants), len(shifts), len(a)))
    sh = np.asarray(shifts)[None, :, None, None, None]
    sl = slants[:, None, None, None, None] * off[None, None]                      # (G, 1, 1, 1, 3)
    for j, sign in enumerate((1.0, -1.0)):
        bx = xl[..., None] + sign * off
        by = np.broadcast_to(ys[..., None], bx.shape)
        lv = _sample(L, bx, by)
        rx = bx[None, None] - d[None, None] - sh - sl                               # (G, S, C, k, 3)
        rv = _sample(R, rx, np.broadcast_to(by[None, None], rx.shape))
        cost[j] = np.abs(lv[None, None] - rv).mean(axis=(3, 4))
    # Per side, the cost profile over the disparity at the line, each at its best plane through the line
    # (slant). The near side matches at the line's disparity, better than at a pixel either way with any
    # slant (at a wrong disparity the match is another structure's; a slanted plane through a wrong
    # disparity can imitate the right one over the band, so every slant competes), and at least 2x better
    # than 3 px either way (the floor test's rule: an untextured or weakly textured side proves nothing).
    ci = np.arange(len(a))
    prof = cost.min(axis=1)                                                       # (2, shifts, C)
    best = cost[:, :, 2].argmin(axis=1)                                           # (2, C)
    c0 = prof[:, 2]
    side_ok = ((c0 <= params.band_max_diff) & (c0 < prof[:, 1]) & (c0 < prof[:, 3])
               & (2.0 * c0 <= np.minimum(prof[:, 0], prof[:, 4])))
    # An occluding boundary: the far side differs from the near side's plane continued across the line
    # (slant -g on the other side; the background is shifted by another disparity). A line whose both sides
    # lie on one plane is on a surface (texture), where LSD's contrast does not change sign.
    flip = len(slants) - 1 - best                                                 # slant -g (symmetric grid)
    far_differs = cost[np.array([1, 0])[:, None], flip, 2, ci[None, :]] > params.band_max_diff
    good = (side_ok & far_differs).any(axis=0)
    # A plain near side (a box's untextured face) matches as well a pixel or more either way (which one
    # wins is the noise's draw), so the 2x rule refuses it, although the lines' positions give the
    # disparity. It is taken when it matches at the noise's level: |l - r| on one plain surface is noise
    # alone, 2 sigma / sqrt(pi) on average for two samples of sigma each (less after the right image's
    # bilinear interpolation and the best slant: the room's plain faces 0.6 sigma), while a textured
    # surface at a wrong disparity differs by its texture (2.1 sigma and up on the blob-textured walls of
    # tests/test_line_vertical.py). Only for a left run without a confirmed candidate.
    plain = c0 <= PLAIN_NOISE_GAIN * noise
    confirmed = np.zeros(len(lr), bool)
    confirmed[a[good]] = True
    by_plain = (plain & far_differs).any(axis=0) & ~confirmed[a]
    good |= by_plain
    a, b, by_plain = a[good], b[good], by_plain[good]
    # A plain face also matches any right run on its own grey (a texture line of the background ending on
    # the face), at other disparities. The same vertical line spans the same rows in both rectified images:
    # a plain candidate sharing 2x the rows of each plain one at another disparity is the line (a choice, as
    # the 2x rule's), the others go; without one, the run keeps all and gets none below.
    a, b = _longest_plain(a, b, by_plain, disp[a, b], (hi - lo)[a, b], len(lr))
    # Periodic texture gives a left run candidates at several disparities: it gets none. Candidates within a
    # pixel of one disparity are one line that the right image's run broke into pieces (a contrast sign
    # change): the one sharing most rows with the left run is kept.
    dg = disp[a, b]
    n = len(lr)
    spread = np.full(n, -np.inf)
    np.maximum.at(spread, a, dg)
    low = np.full(n, np.inf)
    np.minimum.at(low, a, dg)
    one = (spread - low)[a] <= 1.0
    rows = (hi - lo)[a, b]
    order = np.lexsort((-rows, a))                                # per left run, the most shared rows first
    first = np.ones(len(order), bool)
    first[1:] = a[order][1:] != a[order][:-1]
    keep = np.zeros(len(a), bool)
    keep[order[first]] = True
    keep &= one
    # The matched rows: the left run's rows that the agreeing right pieces span (their gaps are sign changes).
    top = np.full(n, np.inf)
    np.minimum.at(top, a, lo[a, b])
    bottom = np.full(n, -np.inf)
    np.maximum.at(bottom, a, hi[a, b])
    a, b = a[keep], b[keep]
    return a, b, top[a], bottom[a]


def _longest_plain(a: np.ndarray, b: np.ndarray, by_plain: np.ndarray, d: np.ndarray, rows: np.ndarray,
                   n: int) -> tuple[np.ndarray, np.ndarray]:
    """The candidates (a left run, b right run) less, per left run, the plain ones (``by_plain``) more than a
    pixel from the disparity ``d`` of its longest plain one (most shared ``rows``), when that one shares 2x
    the rows of each of them; the others unchanged. ``n``: the number of left runs."""
    if not by_plain.any():
        return a, b
    idx = np.nonzero(by_plain)[0]
    best = np.full(n, -1)
    order = idx[np.lexsort((-rows[idx], a[idx]))]                  # per left run, the most shared rows first
    first = np.ones(len(order), bool)
    first[1:] = a[order][1:] != a[order][:-1]
    best[a[order[first]]] = order[first]
    k = best[a[idx]]                                              # each plain candidate's run's longest
    other = np.abs(d[idx] - d[k]) > 1.0
    rival = np.zeros(n)
    np.maximum.at(rival, a[idx][other], rows[idx][other])
    won = rows[k] >= 2.0 * rival[a[idx]]
    drop = np.zeros(len(a), bool)
    drop[idx] = won & other
    return a[~drop], b[~drop]


def band_slants(params: LineParams = LineParams()) -> np.ndarray:
    """Disparity slants (px of disparity per px across the line) tried for a side band: up to the disparity
    gradient limit (Pollard, Mayhew and Frisby: 1 in cyclopean terms, 2/3 px per left-image px), in steps that
    move the outer band by at most half a pixel."""
    lim = 2.0 / 3.0
    n = int(math.ceil(lim * max(params.band_px) / 0.5))
    return np.linspace(-lim, lim, 2 * n + 1)


def add_vertical_matches(left_image: np.ndarray, right_image: np.ndarray, ls: Segments2D, rs: Segments2D,
                         m: StereoMatches, vertical: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                         params: LineParams, grads: Optional[tuple] = None) -> tuple[Segments2D, Segments2D, StereoMatches]:
    """Both images' segments and the matches with the matched vertical lines appended (each its own left
    segment's only, best candidate; score: its appearance, as the edge search's). A match already found
    for a left segment lying along a vertical line (1 px at both ends, within its rows) with the same
    disparity (1 px) is the same edge, seen shorter: it is dropped."""
    lxy, rxy = vertical_lines(left_image, right_image, vertical, fx, fy, cx, cy, params, ls.xy, grads)
    if len(lxy) == 0:
        return ls, rs, m
    gl, gr = grey(left_image), grey(right_image)
    lsides, rsides = side_means(gl, lxy, params), side_means(gr, rxy, params)
    app = np.exp(-0.5 * (np.abs(lsides - rsides).min(axis=1) / params.appearance_sigma) ** 2)
    if len(m):
        E = ls.xy[m.left]                                                    # (K, 4)
        ey = E[:, [1, 3]]                                                    # (K, 2)
        vx = _x_at(lxy[None, :, :], ey[:, :, None])                          # (K, 2, V)
        along = (np.abs(vx - E[:, [0, 2], None]) <= 1.0).all(axis=1)
        g = params.vertical_gap_px
        inside = ((ey.min(axis=1)[:, None] >= lxy[None, :, 1] - g) & (ey.max(axis=1)[:, None] <= lxy[None, :, 3] + g))
        vd = vx - _x_at(rxy[None, :, :], ey[:, :, None])                     # vertical line's disparity at those rows
        same = (np.abs(vd - m.disparity[:, :, None]) <= 1.0).all(axis=1)
        m = m.subset(~(along & inside & same).any(axis=1))
    li = len(ls) + np.arange(len(lxy))
    ri = len(rs) + np.arange(len(rxy))
    disp = np.column_stack((lxy[:, 0] - rxy[:, 0], lxy[:, 2] - rxy[:, 2]))
    cat = np.concatenate
    ls = Segments2D(cat((ls.xy, lxy)), cat((ls.sides, lsides)))
    rs = Segments2D(cat((rs.xy, rxy)), cat((rs.sides, rsides)))
    m = StereoMatches(cat((m.left, li)), cat((m.right, ri)), cat((m.score, app)), cat((m.disparity, disp)),
                      cat((m.best, np.ones(len(li), bool))), cat((m.predicted, np.zeros(len(li), bool))))
    return ls, rs, m
