"""Compiled inner loop of the motion alternation (11.15-11.17), same maths as ``motion.py``.

Why compiled: one alternation step is a 9x9 product, a 3x3 SVD and a few 3x3
products, about a microsecond of arithmetic. In numpy each of those is a call
costing a few microseconds of interpreter overhead on arrays this small, so
the numpy solve spends ~0.35 ms at n = 50, nearly all of it overhead. numba
compiles the same steps to machine code (cached on disk after the first call)
and releases the GIL while it runs, so a vision thread solving poses does not
hold up the control loop.

numba's own ``np.linalg`` needs SciPy's LAPACK, which we do not ship, so the
3x3 SVD here is a one-sided Jacobi (Hestenes) SVD: exact to rounding for 3x3,
with the reflection guard of ``motion._rotation_from_cross_covariance``.

``motion.recover_motion`` calls :func:`solve_from` (and ``recover_motion_robust``
:func:`minimal_hypotheses`) when numba imports and ``VBNAV_NO_JIT`` is unset;
the numpy path stays as the readable reference and the fallback, and
``tests/test_motion_kernel.py`` checks the two agree. The loops allocate
nothing: on arrays this small an allocation costs more than the arithmetic.
"""
from __future__ import annotations

import math

import numpy as np

# Without numba (or with VBNAV_NO_JIT set) AVAILABLE is False: motion.py uses its numpy reference path.
from vbnav.vision.jit import AVAILABLE  # noqa: F401  (the callers ask the kernel module)
from vbnav.vision.jit import kernel as _jit


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
def _svd3_into(H, work, s):
    """H = U diag(s) V^T for a 3x3 H (one-sided Jacobi), s descending, into work[2] = U, work[3] = V.

    work (4, 3, 3) and s (3,) are the caller's buffers (the alternation calls this every step: no
    allocation). work[0] and work[1] are scratch.
    """
    A, V, U, Vs = work[0], work[1], work[2], work[3]
    for i in range(3):
        for j in range(3):
            A[i, j] = H[i, j]
            V[i, j] = 1.0 if i == j else 0.0
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
                sn = c * t
                for k in range(3):
                    ap, aq = A[k, p], A[k, q]
                    A[k, p] = c * ap - sn * aq
                    A[k, q] = sn * ap + c * aq
                    vp, vq = V[k, p], V[k, q]
                    V[k, p] = c * vp - sn * vq
                    V[k, q] = sn * vp + c * vq
        if not rotated:
            break
    n0 = math.sqrt(A[0, 0] * A[0, 0] + A[1, 0] * A[1, 0] + A[2, 0] * A[2, 0])
    n1 = math.sqrt(A[0, 1] * A[0, 1] + A[1, 1] * A[1, 1] + A[2, 1] * A[2, 1])
    n2 = math.sqrt(A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2] + A[2, 2] * A[2, 2])
    # order of the columns by decreasing norm (a stable sort of three)
    o0, o1, o2 = 0, 1, 2
    v0, v1, v2 = n0, n1, n2
    if v1 > v0:
        o0, o1, v0, v1 = o1, o0, v1, v0
    if v2 > v1:
        o1, o2, v1, v2 = o2, o1, v2, v1
        if v1 > v0:
            o0, o1, v0, v1 = o1, o0, v1, v0
    s[0], s[1], s[2] = v0, v1, v2
    tiny = 1e-300 + 1e-14 * v0
    for j in range(3):
        o = o0 if j == 0 else (o1 if j == 1 else o2)
        for k in range(3):
            Vs[k, j] = V[k, o]
            U[k, j] = A[k, o] / s[j] if s[j] > tiny else 0.0
    # Columns of U for (near-)zero singular values: complete an orthonormal basis.
    if s[0] <= tiny:
        for i in range(3):
            for j in range(3):
                U[i, j] = 1.0 if i == j else 0.0
    else:
        if s[1] <= tiny:  # any unit vector orthogonal to u0
            a0, a1, a2 = (1.0, 0.0, 0.0) if abs(U[0, 0]) < 0.9 else (0.0, 1.0, 0.0)
            d = a0 * U[0, 0] + a1 * U[1, 0] + a2 * U[2, 0]
            u0, u1, u2 = a0 - d * U[0, 0], a1 - d * U[1, 0], a2 - d * U[2, 0]
            nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
            U[0, 1], U[1, 1], U[2, 1] = u0 / nu, u1 / nu, u2 / nu
        if s[2] <= tiny:
            U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
            U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
            U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]


@_jit
def svd3(H):
    """H = U diag(s) V^T for a 3x3 H, s descending, U and V orthogonal (one-sided Jacobi)."""
    work = np.empty((4, 3, 3))
    s = np.empty(3)
    _svd3_into(H, work, s)
    return work[2].copy(), s, work[3].copy()


@_jit
def _rotation_into(H, R, work, s):
    """R = argmax_{R in SO(3)} trace(R H) = V diag(1, 1, det(V U^T)) U^T, written into R."""
    _svd3_into(H, work, s)
    U, V = work[2], work[3]
    d = -1.0 if _det3(U) * _det3(V) < 0.0 else 1.0
    for i in range(3):
        for j in range(3):
            R[i, j] = V[i, 0] * U[j, 0] + V[i, 1] * U[j, 1] + d * V[i, 2] * U[j, 2]


@_jit
def rotation_from_cross_covariance(H):
    """argmax_{R in SO(3)} trace(R H) = V diag(1, 1, det(V U^T)) U^T (Arun/Umeyama, reflection-safe)."""
    R = np.empty((3, 3))
    _rotation_into(H, R, np.empty((4, 3, 3)), np.empty(3))
    return R


@_jit
def _apply(R, T, p):
    """R p + T as three scalars (no array allocated: this runs per point, per hypothesis)."""
    return (R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + T[0],
            R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + T[1],
            R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + T[2])


@_jit
def _exp_log_scaled_into(Q, k, out):
    """out = exp(k log Q) for a rotation Q; False (out untouched) when the angle of Q is under 1e-5 rad
    or within 0.14 rad of pi, where the extrapolation is not worth it or not defined."""
    c = 0.5 * (Q[0, 0] + Q[1, 1] + Q[2, 2] - 1.0)
    w0, w1, w2 = 0.5 * (Q[2, 1] - Q[1, 2]), 0.5 * (Q[0, 2] - Q[2, 0]), 0.5 * (Q[1, 0] - Q[0, 1])
    sn = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    theta = math.atan2(sn, c)
    if theta < 1e-5 or theta > 3.0:
        return False
    x, y, z = w0 / sn, w1 / sn, w2 / sn  # unit axis
    a = k * theta
    ca, sa = math.cos(a), math.sin(a)
    t = 1.0 - ca
    out[0, 0], out[0, 1], out[0, 2] = ca + t * x * x, t * x * y - sa * z, t * x * z + sa * y
    out[1, 0], out[1, 1], out[1, 2] = t * x * y + sa * z, ca + t * y * y, t * y * z - sa * x
    out[2, 0], out[2, 1], out[2, 2] = t * x * z - sa * y, t * y * z + sa * x, ca + t * z * z
    return True


@_jit
def _quadratic(E, r):
    acc = 0.0
    for i in range(9):
        row = 0.0
        for j in range(9):
            row += E[i, j] * r[j]
        acc += r[i] * row
    return acc


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
    r = R.reshape(9)  # a view: follows R
    T = _mv(C, r)
    meanD = 0.0
    for i in range(N):
        meanD += abs(D[i])
    bound = tol * max(meanD / N, 1e-300)
    pmax = 0.0
    for i in range(N):
        pmax = max(pmax, _dot(P[i], P[i]))
    pmax = math.sqrt(pmax)
    # The loop works in preallocated buffers: small-array allocations would cost more than the arithmetic.
    work, sv = np.empty((4, 3, 3)), np.empty(3)
    h = np.empty(9)
    R_new, R_acc, Q = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    T_new = np.empty(3)
    converged = False
    it = 1
    while it < max_iter:
        it += 1
        for i in range(9):
            acc = 0.0
            for j in range(9):
                acc += M[i, j] * r[j]
            h[i] = acc
        _rotation_into(h.reshape(3, 3), R_new, work, sv)
        if overrelax > 1.0:
            # Geodesic extrapolation R exp(overrelax log(R^T R_new)). Steps under 1e-5 rad are not
            # extrapolated (as cv2.Rodrigues in the numpy path, which returns zero there): at that size a
            # doubled step only postpones the convergence test.
            for i in range(3):
                for j in range(3):
                    Q[i, j] = R[0, i] * R_new[0, j] + R[1, i] * R_new[1, j] + R[2, i] * R_new[2, j]
            if _exp_log_scaled_into(Q, overrelax, work[0]):
                for i in range(3):
                    for j in range(3):
                        R_acc[i, j] = R[i, 0] * work[0, 0, j] + R[i, 1] * work[0, 1, j] + R[i, 2] * work[0, 2, j]
                if _quadratic(E, R_acc.reshape(9)) < _quadratic(E, R_new.reshape(9)):
                    R_new[:, :] = R_acc
        rn = R_new.reshape(9)
        for i in range(3):
            acc = 0.0
            for j in range(9):
                acc += C[i, j] * rn[j]
            T_new[i] = acc
        dr2 = 0.0
        for j in range(9):
            dr2 += (rn[j] - r[j]) ** 2
        dt2 = (T_new[0] - T[0]) ** 2 + (T_new[1] - T[1]) ** 2 + (T_new[2] - T[2]) ** 2
        R[:, :] = R_new
        T[:] = T_new
        if math.sqrt(dr2) * pmax + math.sqrt(dt2) <= bound:
            converged = True
            break
    depths = np.empty(N)
    ss = 0.0
    for i in range(N):
        x, y, z = _apply(R, T, P[i])
        depths[i] = x * n[i, 0] + y * n[i, 1] + z * n[i, 2]
        nx = math.sqrt(x * x + y * y + z * z)
        if nx > 0.0:
            dx, dy, dz = x / nx - n[i, 0], y / nx - n[i, 1], z / nx - n[i, 2]
            ang = 2.0 * math.asin(min(1.0, 0.5 * math.sqrt(dx * dx + dy * dy + dz * dz)))
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
            x, y, z = _apply(R0, T0, P[i])
            D[i] = x * n[i, 0] + y * n[i, 1] + z * n[i, 2]
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
    if iters < 1:
        raise ValueError("minimal_hypotheses: iters must be >= 1")
    H = samples.shape[0]
    N = P.shape[0]
    Rs = np.empty((H, 3, 3))
    Ts = np.empty((H, 3))
    counts = np.zeros(H, np.int64)
    Ps = np.empty((3, 3))
    ns = np.empty((3, 3))
    D = np.empty(3)
    Hm = np.empty((3, 3))
    cP, cQ = np.empty(3), np.empty(3)
    work, sv = np.empty((4, 3, 3)), np.empty(3)
    for h in range(H):
        R, T = Rs[h], Ts[h]  # views: the hypothesis is written in place
        for k in range(3):
            Ps[k] = P[samples[h, k]]
            ns[k] = n[samples[h, k]]
            D[k] = D0[samples[h, k]]
        for _it in range(iters):
            for a in range(3):
                cP[a] = (Ps[0, a] + Ps[1, a] + Ps[2, a]) / 3.0
                cQ[a] = (D[0] * ns[0, a] + D[1] * ns[1, a] + D[2] * ns[2, a]) / 3.0
            Hm[:, :] = 0.0
            for k in range(3):
                for a in range(3):
                    for b in range(3):
                        Hm[a, b] += (Ps[k, a] - cP[a]) * (D[k] * ns[k, b] - cQ[b])
            _rotation_into(Hm, R, work, sv)
            for a in range(3):
                T[a] = cQ[a] - (R[a, 0] * cP[0] + R[a, 1] * cP[1] + R[a, 2] * cP[2])
            floor = 0.0
            for k in range(3):
                x, y, z = _apply(R, T, Ps[k])
                D[k] = x * ns[k, 0] + y * ns[k, 1] + z * ns[k, 2]
                floor = max(floor, abs(D[k]))
            floor = 1e-9 * (floor + 1e-300)
            for k in range(3):
                D[k] = max(D[k], floor)
        c = 0
        for i in range(N):
            x, y, z = _apply(R, T, P[i])
            nx = math.sqrt(x * x + y * y + z * z)
            if nx > 0.0 and x * n[i, 0] + y * n[i, 1] + z * n[i, 2] > gate * nx:
                c += 1
        counts[h] = c
    return Rs, Ts, counts
