"""Compiled inner loop of the motion alternation (11.15-11.17), same maths as ``motion.py``.

Why compiled: one alternation step is a 9x9 product, a 3x3 SVD and a few 3x3
products, about a microsecond of arithmetic. In numpy each of those is a call
costing a few microseconds of interpreter overhead on arrays this small, so
the numpy solve spent ~0.3 ms at n = 50, nearly all of it overhead. numba
compiles the same steps to machine code (cached on disk after the first call)
and releases the GIL while it runs, so a vision thread solving poses does not
hold up the control loop.

numba's own ``np.linalg`` needs SciPy's LAPACK, which we do not ship, so the
3x3 SVD here is a one-sided Jacobi (Hestenes) SVD: exact to rounding for 3x3,
with the reflection guard of ``motion._rotation_from_cross_covariance``.

``motion.recover_motion`` calls :func:`solve` when numba imports and
``VBNAV_NO_JIT`` is unset; the numpy path stays as the readable reference and
the fallback, and ``tests/test_motion_kernel.py`` checks the two agree.
"""
from __future__ import annotations

import math
import os

import numpy as np

try:
    if os.environ.get("VBNAV_NO_JIT"):
        raise ImportError("VBNAV_NO_JIT is set")
    import numba

    _jit = numba.njit(cache=True, nogil=True)
    AVAILABLE = True
except ImportError:  # the numpy reference path in motion.py is used instead
    AVAILABLE = False

    def _jit(f):
        return f


@_jit
def _det3(m):
    return (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
            - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]))


@_jit
def _mm(A, B):
    """A @ B by loops (numba's @ needs SciPy's BLAS; these matrices are at most 9x9)."""
    m, k = A.shape
    p = B.shape[1]
    out = np.zeros((m, p))
    for i in range(m):
        for j in range(k):
            a = A[i, j]
            if a != 0.0:
                for c in range(p):
                    out[i, c] += a * B[j, c]
    return out


@_jit
def _mv(A, v):
    m, k = A.shape
    out = np.zeros(m)
    for i in range(m):
        acc = 0.0
        for j in range(k):
            acc += A[i, j] * v[j]
        out[i] = acc
    return out


@_jit
def _dot(a, b):
    acc = 0.0
    for i in range(a.shape[0]):
        acc += a[i] * b[i]
    return acc


@_jit
def _inv3(m):
    d = _det3(m)
    out = np.empty((3, 3))
    out[0, 0] = (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]) / d
    out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) / d
    out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) / d
    out[1, 0] = (m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]) / d
    out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) / d
    out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) / d
    out[2, 0] = (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]) / d
    out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) / d
    out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) / d
    return out


@_jit
def svd3(H):
    """H = U diag(s) V^T for a 3x3 H, s descending, U and V orthogonal (one-sided Jacobi)."""
    A = H.copy()
    V = np.eye(3)
    for _sweep in range(30):
        rotated = False
        for p in range(2):
            for q in range(p + 1, 3):
                alpha = A[0, p] * A[0, p] + A[1, p] * A[1, p] + A[2, p] * A[2, p]
                beta = A[0, q] * A[0, q] + A[1, q] * A[1, q] + A[2, q] * A[2, q]
                gamma = A[0, p] * A[0, q] + A[1, p] * A[1, q] + A[2, p] * A[2, q]
                if abs(gamma) <= 1e-15 * math.sqrt(alpha * beta) or gamma == 0.0:
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0.0 else -1.0) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for k in range(3):
                    ap, aq = A[k, p], A[k, q]
                    A[k, p] = c * ap - s * aq
                    A[k, q] = s * ap + c * aq
                    vp, vq = V[k, p], V[k, q]
                    V[k, p] = c * vp - s * vq
                    V[k, q] = s * vp + c * vq
        if not rotated:
            break
    sig = np.empty(3)
    for j in range(3):
        sig[j] = math.sqrt(A[0, j] * A[0, j] + A[1, j] * A[1, j] + A[2, j] * A[2, j])
    order = np.argsort(-sig)
    s = sig[order]
    U = np.empty((3, 3))
    Vs = np.empty((3, 3))
    tiny = 1e-300 + 1e-14 * s[0]
    for j in range(3):
        o = order[j]
        for k in range(3):
            Vs[k, j] = V[k, o]
            U[k, j] = A[k, o] / s[j] if s[j] > tiny else 0.0
    # Columns of U for (near-)zero singular values: complete an orthonormal basis.
    if s[0] <= tiny:
        U[:, :] = np.eye(3)
    else:
        if s[1] <= tiny:  # any unit vector orthogonal to u0
            u0 = U[:, 0]
            a = np.array([1.0, 0.0, 0.0]) if abs(u0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            u1 = a - _dot(a, u0) * u0
            U[:, 1] = u1 / math.sqrt(_dot(u1, u1))
        if s[2] <= tiny:
            U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
            U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
            U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    return U, s, Vs


@_jit
def rotation_from_cross_covariance(H):
    """argmax_{R in SO(3)} trace(R H) = V diag(1, 1, det(V U^T)) U^T (Arun/Umeyama, reflection-safe)."""
    U, _s, V = svd3(H)
    if _det3(U) * _det3(V) < 0.0:
        V[:, 2] = -V[:, 2]
    return _mm(V, U.T.copy())


@_jit
def _log_so3(R):
    """Rotation vector of R (atan2 form, accurate for small angles); zero when too close to pi to be defined."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    w0, w1, w2 = 0.5 * (R[2, 1] - R[1, 2]), 0.5 * (R[0, 2] - R[2, 0]), 0.5 * (R[1, 0] - R[0, 1])
    s = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)  # sin(theta)
    theta = math.atan2(s, c)
    if theta > 3.0:
        return np.zeros(3)
    f = theta / s if s > 1e-300 else 1.0
    return np.array([f * w0, f * w1, f * w2])


@_jit
def _exp_so3(v):
    theta = math.sqrt(_dot(v, v))
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    a = math.sin(theta) / theta
    b = (1.0 - math.cos(theta)) / (theta * theta)
    return np.eye(3) + a * K + b * _mm(K, K)


@_jit
def object_space_maps(P, n, w):
    """The per-solve linear maps of motion._ObjectSpaceIteration: M (9x9), C (3x9), E (9x9).

    w: normalised weights (sum 1); vec(R) is row-major. Everything is built from
    weighted moments of the points and rays in one pass, without allocating per point:
      A[3a+b, 3c+d] = sum w p~_a n_b n_c P_d,  B[3a+b, c] = sum w p~_a n_b n_c,
      G[a, 3c+d] = delta_ac cP_d - sum w n_a n_c P_d,  W = sum w n n^T,
      C = -(I - W)^-1 G,  M = A + B C,
    and with Q_i = I - n_i n_i^T, S_i vec(R) = R P_i, A_i = S_i + C:
      E = sum w A_i^T Q_i A_i = F + G'C + (G'C)^T + C^T (I - W) C,
      F[3a+d, 3c+e] = sum w Q_ac P_d P_e and G'[3a+d, c] = G[a, 3c+d].
    """
    N = P.shape[0]
    cP = np.zeros(3)
    for i in range(N):
        for d in range(3):
            cP[d] += w[i] * P[i, d]
    A = np.zeros((9, 9))
    B = np.zeros((9, 3))
    W = np.zeros((3, 3))
    G = np.zeros((3, 9))
    S2 = np.zeros((3, 3))  # sum w P P^T
    F = np.zeros((9, 9))
    for i in range(N):
        wi = w[i]
        for a in range(3):
            wpa = wi * (P[i, a] - cP[a])
            for b in range(3):
                k = wpa * n[i, b]
                for c in range(3):
                    kc = k * n[i, c]
                    B[3 * a + b, c] += kc
                    for d in range(3):
                        A[3 * a + b, 3 * c + d] += kc * P[i, d]
            for c in range(3):
                wnn = wi * n[i, a] * n[i, c]
                W[a, c] += wnn
                for d in range(3):
                    wnnp = wnn * P[i, d]
                    G[a, 3 * c + d] -= wnnp
                    for e in range(3):
                        F[3 * a + d, 3 * c + e] -= wnnp * P[i, e]
        for d in range(3):
            for e in range(3):
                S2[d, e] += wi * P[i, d] * P[i, e]
    for a in range(3):
        for d in range(3):
            G[a, 3 * a + d] += cP[d]
            for e in range(3):
                F[3 * a + d, 3 * a + e] += S2[d, e]
    IW = np.eye(3) - W
    C = -_mm(_inv3(IW), G)
    M = A + _mm(B, C)
    Gp = np.empty((9, 3))
    for a in range(3):
        for c in range(3):
            for d in range(3):
                Gp[3 * a + d, c] = G[a, 3 * c + d]
    GC = _mm(Gp, C)
    E = F + GC + GC.T + _mm(C.T.copy(), _mm(IW, C))
    return M, C, E


@_jit
def solve(P, n, D, w, max_iter, tol, overrelax):
    """The alternation of motion.recover_motion from depth guesses D; returns R, T, depths, iterations,
    rms ray angle (rad) and whether it converged."""
    N = P.shape[0]
    M, C, E = object_space_maps(P, n, w)
    cP = np.zeros(3)
    for i in range(N):
        for d in range(3):
            cP[d] += w[i] * P[i, d]
    H0 = np.zeros((3, 3))  # first step from the guessed depths (11.15-11.17)
    for i in range(N):
        for a in range(3):
            pa = w[i] * (P[i, a] - cP[a])
            for b in range(3):
                H0[a, b] += pa * D[i] * n[i, b]
    R = rotation_from_cross_covariance(H0)
    r = R.ravel()
    T = _mv(C, r)
    meanD = 0.0
    for i in range(N):
        meanD += abs(D[i])
    bound = tol * max(meanD / N, 1e-300)
    pmax = 0.0
    for i in range(N):
        pmax = max(pmax, _dot(P[i], P[i]))
    pmax = math.sqrt(pmax)
    converged = False
    it = 1
    while it < max_iter:
        it += 1
        R_new = rotation_from_cross_covariance(_mv(M, r).reshape(3, 3))
        if overrelax > 1.0:
            v = _log_so3(_mm(R.T.copy(), R_new))
            # Steps under 1e-5 rad are not extrapolated (as cv2.Rodrigues in the numpy path, which
            # returns zero there): at that size a doubled step only postpones the convergence test.
            if _dot(v, v) >= 1e-10:
                R_acc = _mm(R, _exp_so3(overrelax * v))
                ra, rn = R_acc.ravel(), R_new.ravel()
                if _dot(ra, _mv(E, ra)) < _dot(rn, _mv(E, rn)):
                    R_new = R_acc
        r_new = R_new.ravel().copy()
        T_new = _mv(C, r_new)
        dR = r_new - r
        dT = T_new - T
        change = math.sqrt(_dot(dR, dR)) * pmax + math.sqrt(_dot(dT, dT))
        R, r, T = R_new, r_new, T_new
        if change <= bound:
            converged = True
            break
    depths = np.empty(N)
    ss = 0.0
    for i in range(N):
        X = _mv(R, P[i]) + T
        depths[i] = _dot(X, n[i])
        nx = math.sqrt(_dot(X, X))
        if nx > 0.0:
            d = X / nx - n[i]
            ang = 2.0 * math.asin(min(1.0, 0.5 * math.sqrt(_dot(d, d))))
        else:
            ang = math.pi
        ss += ang * ang
    return R, T, depths, it, math.sqrt(ss / N), converged


@_jit
def solve_from(P, n, R0, T0, D0, weights, angular, max_iter, tol, overrelax):
    """recover_motion's set-up, then :func:`solve`. Initial depths n . (R0 P + T0) when D0 is empty,
    else D0; weights empty means uniform; ``angular`` multiplies them by 1/D^2; they are normalised."""
    N = P.shape[0]
    if D0.shape[0] == 0:
        D = np.empty(N)
        for i in range(N):
            D[i] = _dot(_mv(R0, P[i]) + T0, n[i])
    else:
        D = D0
    w = np.ones(N) if weights.shape[0] == 0 else weights.copy()
    if angular:
        for i in range(N):
            w[i] /= max(abs(D[i]), 1e-12) ** 2
    w /= w.sum()
    return solve(P, n, D, w, max_iter, tol, overrelax)


@_jit
def minimal_hypotheses(P, n, D0, samples, iters, gate):
    """motion._minimal_hypotheses and its scoring: the alternation on each 3-point sample (centroid
    translation) from depths D0, then the number of rays within the angle whose cosine is ``gate``.
    Returns R (H, 3, 3), T (H, 3), counts (H,)."""
    H = samples.shape[0]
    N = P.shape[0]
    Rs = np.empty((H, 3, 3))
    Ts = np.empty((H, 3))
    counts = np.zeros(H, np.int64)
    Ps = np.empty((3, 3))
    ns = np.empty((3, 3))
    D = np.empty(3)
    Hm = np.empty((3, 3))
    R = np.eye(3)
    T = np.zeros(3)
    for h in range(H):
        for k in range(3):
            Ps[k] = P[samples[h, k]]
            ns[k] = n[samples[h, k]]
            D[k] = D0[samples[h, k]]
        for _it in range(iters):
            cP = (Ps[0] + Ps[1] + Ps[2]) / 3.0
            cQ = (D[0] * ns[0] + D[1] * ns[1] + D[2] * ns[2]) / 3.0
            Hm[:, :] = 0.0
            for k in range(3):
                for a in range(3):
                    for b in range(3):
                        Hm[a, b] += (Ps[k, a] - cP[a]) * (D[k] * ns[k, b] - cQ[b])
            R = rotation_from_cross_covariance(Hm)
            T = cQ - _mv(R, cP)
            floor = 0.0
            for k in range(3):
                D[k] = _dot(_mv(R, Ps[k]) + T, ns[k])
                floor = max(floor, abs(D[k]))
            floor = 1e-9 * (floor + 1e-300)
            for k in range(3):
                D[k] = max(D[k], floor)
        Rs[h] = R
        Ts[h] = T
        c = 0
        for i in range(N):
            X = _mv(R, P[i]) + T
            nx = math.sqrt(_dot(X, X))
            if nx > 0.0 and _dot(X, n[i]) > gate * nx:
                c += 1
        counts[h] = c
    return Rs, Ts, counts
