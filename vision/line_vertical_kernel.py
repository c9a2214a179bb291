"""Compiled core of ``line_vertical.pencil_runs``: ridges, their support of the columns, the columns' runs and
each run's weighted line fit, with the same arithmetic as the numpy reference (``line_vertical.column_runs``).

Why compiled: the numpy version makes ~40 passes over 640x480 arrays (a dilation, masks, three scatters, a
closing, an erosion, a transpose, six cumulative sums over the candidate columns) and cost 4.4 ms an image,
8.9 ms of the fast loop's frame (two images; cProfile over laps 2-3 of ``benchmarks/line_map.py``). Here
the ridge test is one vectorised pass along each row, the only image-sized arrays are the support counts and
the closed support (uint8), and the weights are summed again only down the few tens of columns that hold a
run long enough: 0.9-1.2 ms an image against 4.6-5.2 ms for the reference, same images, same run.

The arithmetic is the reference's, operation for operation, so the runs are bit-identical
(``tests/test_line_vertical.py`` compares the two on rendered rooms and noise):

- the ridge test and the sub-pixel offset are float32 (numpy casts a Python scalar to the array's float32:
  the threshold is passed as float32);
- the support of a column adds the ridge's own weight first, then the one from its left neighbour, then the
  one from its right, the scatters' order;
- the sums over a run are differences of running sums (``np.cumsum`` accumulates in order);
- a column is looked at only when an erosion by ``2 (L // 2) + 1`` rows keeps part of its closed support
  (L = ceil(min_length_px); at the image's border the erosion ignores rows outside it), as in the reference.

``line_vertical.pencil_runs`` uses :func:`column_runs` when numba imports and ``VBNAV_NO_JIT`` is unset;
otherwise its numpy path, which stays as the readable reference. :func:`warm_up` compiles it (7-8 s on this VM
the first time, 0.4-0.8 s from numba's disk cache afterwards, as the machine runs) before a vision thread's first frame.
"""
from __future__ import annotations

import math

import numpy as np

# Without numba (or with VBNAV_NO_JIT set) AVAILABLE is False: line_vertical uses its numpy path.
from vbnav.vision.jit import AVAILABLE  # noqa: F401  (the callers ask the kernel module)
from vbnav.vision.jit import kernel as _jit


@_jit
def _offset(M, y, x):
    """A ridge's sub-pixel offset from column x: its parabola through M at x - 1, x, x + 1 (float32, as the
    reference; 0 where the three do not curve down)."""
    a, b, c = M[y, x - 1], M[y, x], M[y, x + 1]
    curv = a - np.float32(2.0) * b + c
    return np.float32(0.5) * (a - c) / curv if curv < 0 else np.float32(0.0)


@_jit
def _ridge(M, gy, y, x, thr):
    """(is a ridge, sub-pixel offset): a local maximum of M along the row above ``thr`` with the gradient
    across the columns, and its parabola's offset."""
    b = M[y, x]
    if not ((b >= M[y, x - 1]) & (b >= M[y, x + 1]) & (b > thr) & (abs(gy[y, x]) < b)):
        return False, np.float32(0.0)
    return True, _offset(M, y, x)


@_jit
def _support(M, gy, thr, hi, lo):
    """How many ridges support each pixel's column: its own and a neighbour's within the tolerance."""
    H, W = M.shape
    S = np.zeros((H, W), np.uint8)
    is_r = np.zeros(W, np.bool_)
    for y in range(H):
        m, g = M[y], gy[y]
        for x in range(2, W - 2):                 # not the Sobel's border columns; _ridge's test, branch-free
            b = m[x]                              # (so it vectorises): most pixels are no ridge
            is_r[x] = (b >= m[x - 1]) & (b >= m[x + 1]) & (b > thr) & (abs(g[x]) < b)
        for x in range(2, W - 2):
            if is_r[x]:
                o = _offset(M, y, x)
                S[y, x] += 1
                if o >= hi:
                    S[y, x + 1] += 1
                if o <= lo:
                    S[y, x - 1] += 1
    return S


@_jit
def _morph_rows(B, h, grow):
    """B dilated (``grow``) or eroded along the columns by a 2h + 1 row element, rows outside ignored."""
    H, W = B.shape
    out = np.empty_like(B)
    for y in range(H):
        y0, y1 = max(0, y - h), min(H, y + h + 1)
        for x in range(W):
            out[y, x] = B[y0, x]
        for k in range(y0 + 1, y1):
            for x in range(W):
                out[y, x] = max(out[y, x], B[k, x]) if grow else min(out[y, x], B[k, x])
    return out


@_jit
def _column_run(C, x, y, he, min_length):
    """The next run of column x at or after row y: (first, last, kept, holds), or first = -1 at the end.
    Kept: at least ``min_length`` rows; holds: part of it survives an erosion by 2 he + 1 rows (rows
    outside the image ignored: the reference's candidate-column test)."""
    H = C.shape[0]
    while y < H and C[y, x] == 0:
        y += 1
    if y == H:
        return -1, -1, False, False
    a = y
    while y < H and C[y, x] != 0:
        y += 1
    b = y - 1
    lo_r = a if a == 0 else a + he
    hi_r = b if b == H - 1 else b - he
    return a, b, b - a + 1 >= min_length, lo_r <= hi_r


@_jit
def _runs(C, he, min_length):
    """(K, 3) column, first and last row of the closed support's runs at least ``min_length`` long, in
    columns where one run survives an erosion by 2 he + 1 rows (the reference's candidate columns),
    sorted by column then row."""
    H, W = C.shape
    # The longest run of each column, in one vectorised pass along the rows: only columns holding one of
    # min_length rows can hold a run to keep (a few tens of 640).
    count = np.zeros(W, np.int32)
    longest = np.zeros(W, np.int32)
    for y in range(H):
        c = C[y]
        for x in range(W):
            count[x] = (count[x] + 1) * (c[x] != 0)
            longest[x] = max(longest[x], count[x])
    kept = np.zeros(W, np.int64)                  # runs kept per candidate column (0: not a candidate)
    for x in range(W):
        if longest[x] >= min_length:
            holds, a, b = False, 0, -1
            while True:
                a, b, keep, hold = _column_run(C, x, b + 1, he, min_length)
                if a < 0:
                    break
                kept[x] += keep
                holds = holds or hold
            if not holds:
                kept[x] = 0
    found = np.zeros((kept.sum(), 3), np.int64)
    n = 0
    for x in range(W):
        b = -1
        while kept[x] > 0:
            a, b, keep, hold = _column_run(C, x, b + 1, he, min_length)
            if a < 0:
                break
            if keep:
                found[n, 0], found[n, 1], found[n, 2] = x, a, b
                n += 1
    return found


@_jit
def _column_sums(M, gy, S, thr, hi, lo, x, cum):
    """Running sums down column x (as np.cumsum): support, weight, weighted position, and those times the
    row and the row squared. A pixel's weight adds its own ridge's, then its left neighbour's right-hand
    share, then its right neighbour's left-hand share: the reference's scatter order."""
    H, W = M.shape
    for y in range(H):
        wt, wp = 0.0, 0.0
        if 2 <= x < W - 2:
            r, o = _ridge(M, gy, y, x, thr)
            if r:
                wt = np.float64(M[y, x])
                wp = wt * (np.float64(x) + np.float64(o))
        if 3 <= x < W - 1:
            r, o = _ridge(M, gy, y, x - 1, thr)
            if r and o >= hi:
                bw = np.float64(M[y, x - 1])
                wt += bw
                wp += bw * (np.float64(x - 1) + np.float64(o))
        if 1 <= x < W - 3:
            r, o = _ridge(M, gy, y, x + 1, thr)
            if r and o <= lo:
                bw = np.float64(M[y, x + 1])
                wt += bw
                wp += bw * (np.float64(x + 1) + np.float64(o))
        fr = np.float64(y)
        wr = wt * fr
        cum[0, y + 1] = cum[0, y] + np.float64(S[y, x])
        cum[1, y + 1] = cum[1, y] + wt
        cum[2, y + 1] = cum[2, y] + wp
        cum[3, y + 1] = cum[3, y] + wr
        cum[4, y + 1] = cum[4, y] + wr * fr
        cum[5, y + 1] = cum[5, y] + wp * fr


@_jit
def column_runs(M, gy, thr, tol, gap, min_length, sigma_perp):
    """(K, 4) runs as the reference builds them (column, first row, last row, strength), before the
    stronger-of-two-neighbours rule: sorted by column then first row. ``thr``: float32 ridge threshold."""
    H, W = M.shape
    hi, lo = np.float32(1.0 - tol), np.float32(tol - 1.0)
    S = _support(M, gy, thr, hi, lo)
    B = np.empty_like(S)                          # supported at all
    for y in range(H):
        for x in range(W):
            B[y, x] = S[y, x] != 0
    if gap > 0:
        hc = (gap + 1) // 2
        B = _morph_rows(_morph_rows(B, hc, True), hc, False)
    found = _runs(B, int(math.ceil(min_length)) // 2, min_length)
    out = np.zeros((len(found), 4))
    n_out = 0
    cum = np.zeros((6, H + 1))
    x_done = -1
    for i in range(len(found)):
        x, a, b = found[i, 0], found[i, 1], found[i, 2]
        if x != x_done:
            _column_sums(M, gy, S, thr, hi, lo, x, cum)
            x_done = x
        n = cum[0, b + 1] - cum[0, a]
        sw = cum[1, b + 1] - cum[1, a]
        swp = cum[2, b + 1] - cum[2, a]
        swr = cum[3, b + 1] - cum[3, a]
        swrr = cum[4, b + 1] - cum[4, a]
        swrp = cum[5, b + 1] - cum[5, a]
        length = b - a + 1
        if not 2 * n >= length:
            continue
        sw = max(sw, 1e-9)
        rbar, pbar = swr / sw, swp / sw
        # The ridges' weighted line fit stays vertical within 3 sigma of its slope (the reference's rule).
        slope = (swrp - rbar * swp) / max(swrr - rbar * swr, 1e-9)
        if not abs(slope) * length <= 3.0 * sigma_perp * math.sqrt(12.0 / max(n, 1.0)):
            continue
        out[n_out, 0], out[n_out, 1], out[n_out, 2], out[n_out, 3] = pbar, a, b, sw / max(n, 1.0)
        n_out += 1
    return out[:n_out]


def warm_up() -> None:
    """Compile (or load from numba's cache) now, not in a vision thread's first frame."""
    if AVAILABLE:
        M = np.zeros((40, 8), np.float32)
        M[:, 4] = 10.0
        column_runs(M, np.zeros_like(M), np.float32(1.0), 0.75, 4, 25.0, 0.3)
