"""The joint fit's compiled residuals and Jacobian (`align.kernels.fit_residuals`,
`fit_jacobian`) against the numpy version they replaced, on models built from real scans (the
five ACFR chessboard captures) and a twin scan (a board with a thickness: the side face's term):
the same numbers to rounding, at the estimate and at poses moved off it, with a range offset.

The compiled loops multiply and add where numpy's matrix products fuse them (BLAS's FMA), so
the last bits may differ: residuals agree to 1e-12 of their scale, the Jacobian's rotation
columns (forward differences of 1e-7 rad) to 1e-7 of theirs.
"""

from __future__ import annotations

import numpy as np
import pytest

import align
from align import rays as rays_mod
from align.geometry import board_coordinates, rotation
from align.segment import find_board
from tests.conftest import DATA_DIR
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim

ACFR_BOARD = align.BoardSpec(0.61, 0.85, thickness=0.0)


def _coords(rot: np.ndarray, theta: np.ndarray, o: np.ndarray, u: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Board coordinates X, Z of rays (origins o, directions u in {L}) and their directions in
    {O}, for the rotation ``rot`` of pose ``theta`` (the numpy version's helper)."""
    d = u @ rot.T
    oo = o @ rot.T + theta[:3]
    lam = -oo[:, 1] / d[:, 1]
    return oo[:, 0] + lam * d[:, 0], oo[:, 2] + lam * d[:, 2], d


def residuals_reference(model: rays_mod._Model, theta: np.ndarray) -> np.ndarray:
    """`Model.residuals` as numpy calls (before the kernel)."""
    rot = rotation(theta[3], theta[4], theta[5])
    o_r, u_r, d_r = model._range
    lam = -(o_r @ rot[1] + theta[1]) / (u_r @ rot[1])
    rr = (d_r - model.offset - lam) / model.sigma_r
    xh, zh, dh = _coords(rot, theta, *model._ubh)
    xm, zm, _ = _coords(rot, theta, *model._ubm)
    sgn = model._usign
    mid_x = 0.5 * (xh + xm)
    mid_z = 0.5 * (zh + zm)
    t = model.board.thickness
    ext_x = t * np.maximum(0.0, -sgn * dh[:, 0] / dh[:, 1])
    ext_z = t * np.maximum(0.0, -sgn * dh[:, 2] / dh[:, 1])
    e = np.where(model._uvert, sgn * (model.board.width / 2 + ext_x) - mid_x,
                 sgn * (model.board.height / 2 + ext_z) - mid_z)
    return np.concatenate((rr, e / model._usd))


def jacobian_reference(model: rays_mod._Model, theta: np.ndarray, f0: np.ndarray
                       ) -> np.ndarray:
    """`Model.jacobian` as numpy calls (before the kernel)."""
    rot = rotation(theta[3], theta[4], theta[5])
    vert = model._uvert
    j = np.empty((len(f0), 6))
    u_r = model._range[1]
    nr = len(u_r)
    j[:nr, 0] = 0.0
    j[:nr, 1] = (1.0 / (u_r @ rot[1])) / model.sigma_r
    j[:nr, 2] = 0.0
    sd = model._usd

    def d_dty(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dlam = -1.0 / (u @ rot[1])
        return dlam * (u @ rot[0]), dlam * (u @ rot[2])

    xh_t, zh_t = d_dty(model._ubh[1])
    xm_t, zm_t = d_dty(model._ubm[1])
    j[nr:, 0] = np.where(vert, -1.0, 0.0) / sd
    j[nr:, 2] = np.where(vert, 0.0, -1.0) / sd
    j[nr:, 1] = -0.5 * np.where(vert, xh_t + xm_t, zh_t + zm_t) / sd
    for i in range(3, 6):
        t = theta.copy()
        t[i] += 1e-7
        j[:, i] = (residuals_reference(model, t) - f0) / 1e-7
    return j


def _model(scan, board: align.BoardSpec, hints: align.Hints) -> tuple[rays_mod._Model,
                                                                      np.ndarray]:
    """The fit's model for one scan at its estimate, built as `rays._fit` builds it."""
    est = align.estimate(scan, board=board, hints=hints)
    assert est.success, est.diagnostics
    theta = est.pose.as_array()
    seg = find_board(scan, board, hints)
    rays = rays_mod._candidates([scan], [seg], theta, board)
    _, _, lam = board_coordinates(theta, rays.origin, rays.direction)
    sigma_r = 0.014
    lab = rays_mod._labels(rays, lam, sigma_r)
    model = rays_mod._build_model(rays, lab, theta, board, sigma_r, hints.edge_blur)
    model.classify(theta, 0.002, True)
    model.assign(theta)
    return model, theta


@pytest.fixture(scope="module")
def models() -> list[tuple[rays_mod._Model, np.ndarray]]:
    hints = align.Hints(expected_distance=1.8)
    out = [_model(read_pcd_scans(p)[0], ACFR_BOARD, hints)
           for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    twin = BenchSim(seed=3).scan()
    out.append(_model(twin, align.BoardSpec(), align.Hints()))
    assert out[-1][0].board.thickness > 0
    return out


def test_compiled_residuals_and_jacobian_match_numpy_on_real_scans(models):
    rng = np.random.default_rng(7)
    for model, theta in models:
        assert len(model._range[0]) > 20 and len(model._usd) > 5
        for k in range(4):
            t = theta + (rng.normal(size=6) * [3e-3, 3e-3, 3e-3, 5e-3, 5e-3, 5e-3] if k else 0)
            model.offset = 0.0 if k < 2 else 0.01
            want = residuals_reference(model, t)
            got = model.residuals(t)
            scale = np.max(np.abs(want))
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)
            jw = jacobian_reference(model, t, want)
            jg = model.jacobian(t, want)
            for c in range(6):
                col = np.max(np.abs(jw[:, c])) + 1.0
                tol = (1e-12 if c < 3 else 1e-7) * col
                np.testing.assert_allclose(jg[:, c], jw[:, c], rtol=0, atol=tol, err_msg=c)
        model.offset = 0.0


def test_msac_ransac_is_numpys_scoring():
    """`plane.ransac(truncated=True)` (the rays' start plane), scored by `kernels.msac_best`,
    against numpy's scoring of the same draws (`plane._ransac_scored`): the same plane and
    inliers on point sets of real and twin scans (a board's returns and its surround, which
    hold hypotheses of near-equal cost), every choice certain or left to numpy. And two
    identical hypotheses (a triple drawn twice): not certain, so numpy's first minimum."""
    from align import kernels, plane

    scans = [read_pcd_scans(p)[0] for p in sorted((DATA_DIR / "acfr-vlp16").glob("pose*_full.pcd"))]
    sim = BenchSim(seed=3)
    scans += [sim.scan() for _ in range(2)]
    compared = certain = 0
    for s in scans:
        m = s.distance > 0
        pts_all = np.column_stack((s.x[m], s.y[m], s.z[m]))
        near = pts_all[np.linalg.norm(pts_all, axis=1) < 3.5]
        for seed in range(4):
            rng = np.random.default_rng(seed)
            pts = near[rng.choice(len(near), min(600, len(near)), replace=False)]
            for threshold in (0.04, 0.01):
                tri = np.random.default_rng(seed + 10).integers(0, len(pts), size=(100, 3))
                want = plane._ransac_scored(pts, tri, threshold, True)
                got = plane.ransac(pts, threshold, np.random.default_rng(seed + 10), 100,
                                   truncated=True)
                np.testing.assert_array_equal(got[0], want[0])
                assert got[1] == want[1]
                np.testing.assert_array_equal(got[2], want[2])
                compared += 1
                certain += kernels.msac_best(np.ascontiguousarray(pts.T), tri, threshold)[1]
    assert compared >= 50
    assert certain >= 0.9 * compared  # the compiled choice, not numpy's, was tested
    tri = np.array([[0, 1, 2], [3, 4, 5], [0, 1, 2]])
    pts = np.random.default_rng(1).normal(size=(50, 3))
    best, certain, _ = kernels.msac_best(np.ascontiguousarray(pts.T), tri, 0.04)
    if best in (0, 2):
        assert not certain
