"""The compiled alternation (vision/motion_kernel.py) against the numpy reference in vision/motion.py."""
from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from vbnav.vision import motion, motion_kernel as mk

needs_kernel = pytest.mark.skipif(not mk.AVAILABLE, reason="numba disabled (VBNAV_NO_JIT) or not installed")


def test_numba_is_what_the_solver_uses():
    # numba is a dependency: a silent fallback to the 10x slower numpy path would be a regression.
    if os.environ.get("VBNAV_NO_JIT"):
        pytest.skip("VBNAV_NO_JIT is set")
    assert mk.AVAILABLE, "numba did not import: vision/motion.py is on its slow numpy path"


def _cases(rng):
    for k in range(400):
        H = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-4, 4)
        if k % 5 == 1:
            H[:, 2] = 2.0 * H[:, 0]  # rank 2
        elif k % 5 == 2:
            H = -H  # det < 0: the unconstrained optimum is a reflection
        elif k % 5 == 3:
            H = np.outer(rng.normal(size=3), rng.normal(size=3))  # rank 1
        yield H


@needs_kernel
def test_svd3_factorises_with_orthogonal_factors_and_sorted_values(rng):
    for H in _cases(rng):
        U, s, V = mk.svd3(H)
        scale = np.abs(H).max()
        np.testing.assert_allclose((U * s) @ V.T, H, atol=1e-12 * scale)
        np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
        assert s[0] >= s[1] >= s[2] >= 0
        np.testing.assert_allclose(s, np.linalg.svd(H, compute_uv=False), atol=1e-12 * scale)
    U, s, V = mk.svd3(np.zeros((3, 3)))
    assert np.all(s == 0) and np.allclose(U.T @ U, np.eye(3))


@needs_kernel
def test_rotation_matches_the_reference_and_is_proper(rng):
    for H in _cases(rng):
        R = mk.rotation_from_cross_covariance(H)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        if np.linalg.svd(H, compute_uv=False)[1] > 1e-9 * np.abs(H).max():  # unique optimum
            np.testing.assert_allclose(R, motion._rotation_from_cross_covariance(H), atol=1e-9)
            # and it is the optimum: no rotation nearby does better
            for _ in range(5):
                dR = cv2.Rodrigues(rng.normal(0, 1e-3, 3))[0]
                assert np.trace(R @ H) >= np.trace(dR @ R @ H) - 1e-12 * np.abs(H).max()


@needs_kernel
def test_geodesic_extrapolation_matches_rodrigues(rng):
    out = np.empty((3, 3))
    for angle in (2e-5, 1e-3, 0.5, 1.4, 2.9):
        axis = rng.normal(size=3)
        v = axis / np.linalg.norm(axis) * angle
        Q = cv2.Rodrigues(v)[0]
        for k in (1.0, 2.0, 0.5):
            assert mk._exp_log_scaled_into(Q, k, out)
            np.testing.assert_allclose(out, cv2.Rodrigues(k * v)[0], atol=1e-9)
    for angle in (0.0, 5e-6, 3.1):  # too small to matter, or too close to pi to be defined
        assert not mk._exp_log_scaled_into(cv2.Rodrigues(np.array([0.0, 0.0, angle]))[0], 2.0, out)


def _scene(rng, n, noise):
    P = np.column_stack((rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(3, 10, n)))
    R = cv2.Rodrigues(rng.normal(0, 0.2, 3))[0]
    T = rng.normal(0, 0.4, 3)
    X = P @ R.T + T
    rays = X / np.linalg.norm(X, axis=1, keepdims=True) + rng.normal(0, noise, (n, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    prior = (R @ cv2.Rodrigues(rng.normal(0, 0.02, 3))[0], T + rng.normal(0, 0.03, 3))
    return P, rays, prior


@needs_kernel
def test_object_space_maps_match_the_reference(rng):
    for n in (3, 7, 60):
        P, rays, _ = _scene(rng, n, 1e-3)
        w = rng.uniform(0.2, 3.0, n)
        w /= w.sum()
        ref = motion._ObjectSpaceIteration(P, rays, w)
        M, C, E = mk.object_space_maps(P, rays, w)
        np.testing.assert_allclose(M, ref.M, atol=1e-11)
        np.testing.assert_allclose(C, ref.C, atol=1e-11)
        np.testing.assert_allclose(E, ref.E, atol=1e-10)


@needs_kernel
@pytest.mark.parametrize("angular", [False, True])
@pytest.mark.parametrize("overrelax", [1.0, 2.0])
def test_compiled_solve_is_the_reference_solve(rng, angular, overrelax):
    for n in (3, 6, 50, 200):
        for _ in range(10):
            P, rays, prior = _scene(rng, n, 2e-3)
            D = np.einsum("ij,ij->i", P @ prior[0].T + prior[1], rays)
            w = 1.0 / D ** 2 if angular else None
            ref = motion._recover_motion_numpy(P, rays, D, w, 200, 1e-5, overrelax)
            ws = np.full(n, 1.0 / n) if w is None else w / w.sum()
            R, T, depths, it, res, conv = mk.solve(P, rays, D, ws, 200, 1e-5, overrelax)
            assert it == ref.iterations and conv == ref.converged
            np.testing.assert_allclose(R, ref.R, atol=1e-9)
            np.testing.assert_allclose(T, ref.T, atol=1e-9)
            np.testing.assert_allclose(depths, ref.depths, atol=1e-9)
            assert res == pytest.approx(ref.residual, rel=1e-6, abs=1e-9)  # rad


@needs_kernel
@pytest.mark.parametrize("start", ["prior", "depths", "cold"])
def test_recover_motion_gives_the_same_answer_with_and_without_the_kernel(rng, monkeypatch, start):
    for angular in (False, True):
        for n in (3, 6, 50):
            P, rays, prior = _scene(rng, n, 2e-3)
            kwargs = dict(angular=angular, weights=rng.uniform(0.5, 2.0, n))
            if start == "prior":
                kwargs["prior"] = prior
            elif start == "depths":
                kwargs["depths"] = np.linalg.norm(P, axis=1)
            fast = motion.recover_motion(P, rays, **kwargs)
            monkeypatch.setattr(mk, "AVAILABLE", False)
            ref = motion.recover_motion(P, rays, **kwargs)
            monkeypatch.setattr(mk, "AVAILABLE", True)
            assert fast.iterations == ref.iterations
            np.testing.assert_allclose(fast.R, ref.R, atol=1e-9)
            np.testing.assert_allclose(fast.T, ref.T, atol=1e-9)
            np.testing.assert_allclose(fast.depths, ref.depths, atol=1e-9)


@needs_kernel
def test_compiled_hypotheses_are_the_reference_hypotheses(rng, monkeypatch):
    P, rays, prior = _scene(rng, 40, 1e-3)
    rays[:6] = rays[5::-1].copy()  # swapped rays: gross outliers
    D0 = np.einsum("ij,ij->i", P @ prior[0].T + prior[1], rays)
    samples = motion._three_distinct(rng, 40, 64)
    gate = np.cos(0.01)
    fast = motion._scored_hypotheses(P, rays, D0, samples, 8, gate)
    monkeypatch.setattr(mk, "AVAILABLE", False)
    ref = motion._scored_hypotheses(P, rays, D0, samples, 8, gate)
    np.testing.assert_allclose(fast[0], ref[0], atol=1e-9)
    np.testing.assert_allclose(fast[1], ref[1], atol=1e-9)
    np.testing.assert_array_equal(fast[2], ref[2])
    assert ref[2].max() >= 30  # some samples are all inliers and find the consensus


@needs_kernel
def test_robust_solve_is_the_same_with_and_without_the_kernel(rng, monkeypatch):
    P, rays, prior = _scene(rng, 60, 5e-4)
    rays[:6] = rays[5::-1].copy()  # swapped rays: gross outliers
    fast = motion.recover_motion_robust(P, rays, prior=prior, angular=True, rng=np.random.default_rng(1))
    monkeypatch.setattr(mk, "AVAILABLE", False)
    ref = motion.recover_motion_robust(P, rays, prior=prior, angular=True, rng=np.random.default_rng(1))
    np.testing.assert_array_equal(fast.inliers, ref.inliers)
    assert not fast.inliers[:6].any() and fast.inliers[6:].all()
    assert fast.hypotheses == ref.hypotheses and fast.iterations == ref.iterations
    np.testing.assert_allclose(fast.R, ref.R, atol=1e-9)
    np.testing.assert_allclose(fast.T, ref.T, atol=1e-9)


@needs_kernel
def test_warm_up_compiles_every_signature_the_solvers_use(rng):
    # After warm_up, solving (as the VSLAM does: prior, angular weights, robust) compiles nothing new,
    # so no first-frame stall in the vision thread.
    motion.warm_up()
    kernels = (mk.solve_from, mk.minimal_hypotheses)
    before = [len(k.signatures) for k in kernels]
    assert all(before)
    P, rays, prior = _scene(rng, 80, 1e-3)
    motion.recover_motion_robust(P, rays, prior=prior, angular=True, weights=rng.uniform(0.5, 1, 80), rng=rng)
    motion.recover_motion(P[::2], rays[::2], prior=prior, angular=True)   # strided input
    motion.recover_motion(P, rays, depths=np.linalg.norm(P, axis=1))
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = prior
    motion.recover_motion(P, rays, prior=(M[:3, :3], M[:3, 3]))              # strided prior (a 4x4's views)
    motion.recover_motion_robust(P, rays, prior=(M[:3, :3], M[:3, 3]), angular=True, rng=rng)
    assert [len(k.signatures) for k in kernels] == before


def test_the_kernels_compile_where_no_cache_folder_can_be_written():
    """A service account without a home, running an installation it cannot write, gives numba no place for its
    disk cache: ``njit(cache=True)`` then raises at import ("no locator available") and every vbnav command
    stopped with a traceback. The kernels are compiled without the cache there (vision/jit.py). numba's
    locators are taken away here, as that user has none; root could write anywhere."""
    import subprocess
    import sys
    code = ("import numba.core.caching as c\n"
            "c.CacheImpl._locator_classes = []\n"
            "import numpy as np\n"
            "from vbnav.vision import motion_kernel as mk, line_vertical_kernel as lv\n"
            "assert mk.AVAILABLE and lv.AVAILABLE\n"
            "print(mk._det3(np.diag([1.0, 2.0, 3.0])))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "6.0"


def test_without_the_fallback_numba_refuses_to_cache_there():
    """The condition the test above recreates is the one numba refuses (so that test does test the fallback)."""
    import subprocess
    import sys
    code = ("import numba, numba.core.caching as c\n"
            "c.CacheImpl._locator_classes = []\n"
            "def f(x):\n    return x\n"
            "numba.njit(cache=True)(f)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "no locator available" in r.stderr
