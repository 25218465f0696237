"""The joint fit's compiled residuals and Jacobian (`align.fit.lsq_kernels.fit_residuals`,
`jacobian_into`) against the numpy version they replaced, on models built from real scans (the
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
from align.fit.labels import labels_ordered
from align.fit.model import Model, build_model
from align.fit.rays import candidates_at
from align.geometry import board_coordinates
from align.params import RaysParams
from align.plane import fit as plane
from align.plane.kernels import msac_best
from align.search.board import find_board
from tests import naive
from tests.conftest import DATA_DIR
from twin.lidar.pcd import read_pcd_scans
from twin.sim.bench import BenchSim

ACFR_BOARD = align.BoardSpec(0.61, 0.85, thickness=0.0)
#: The method's tuning, as the estimate uses it by default.
P = RaysParams()


def _model(scan, board: align.BoardSpec, hints: align.Hints) -> tuple[Model,
                                                                      np.ndarray]:
    """The fit's model for one scan at its estimate, built as `align.fit.lsq.fit_from` builds it."""
    est = align.estimate(scan, board=board, hints=hints)
    assert est.success, est.diagnostics
    theta = est.pose.as_array()
    seg = find_board(scan, board, hints)
    rays = candidates_at([scan], [seg], theta, board, p=P)[0]
    _, _, lam = board_coordinates(theta, rays.origin, rays.direction)
    sigma_r = 0.014
    lab = labels_ordered(rays, lam, sigma_r, p=P)[0]
    model = build_model(rays, lab, theta, board, sigma_r, hints.edge_blur, p=P)
    model.classify(theta, 0.002, True)
    model.assign(theta)
    return model, theta


@pytest.fixture(scope="module")
def models() -> list[tuple[Model, np.ndarray]]:
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
        assert np.count_nonzero(model.use_range) > 20 and np.count_nonzero(model.edge_kind) > 5
        for k in range(4):
            t = theta + (rng.normal(size=6) * [3e-3, 3e-3, 3e-3, 5e-3, 5e-3, 5e-3] if k else 0)
            model.offset = 0.0 if k < 2 else 0.01
            want = naive.residuals(model, t)
            got = model.residuals(t)
            scale = np.max(np.abs(want))
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)
            jw = naive.jacobian(model, t, want)
            jg = model.jacobian(t, want)
            for c in range(6):
                col = np.max(np.abs(jw[:, c])) + 1.0
                tol = (1e-12 if c < 3 else 1e-7) * col
                np.testing.assert_allclose(jg[:, c], jw[:, c], rtol=0, atol=tol, err_msg=c)
        model.offset = 0.0


def test_msac_ransac_is_numpys_scoring():
    """`plane.ransac(truncated=True)` (the rays' start plane), scored by `msac_best`,
    against numpy's scoring of the same draws (`tests.naive.ransac_scored`): the same plane and
    inliers on point sets of real and twin scans (a board's returns and its surround, which
    hold hypotheses of near-equal cost), every choice certain or left to numpy. And two
    identical hypotheses (a triple drawn twice): not certain, so numpy's first minimum."""
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
                want = naive.ransac_scored(pts, tri, threshold, True)
                got = plane.ransac(pts, threshold, np.random.default_rng(seed + 10), 100,
                                   truncated=True)
                np.testing.assert_array_equal(got[0], want[0])
                assert got[1] == want[1]
                np.testing.assert_array_equal(got[2], want[2])
                compared += 1
                certain += msac_best(np.ascontiguousarray(pts.T), tri, threshold)[1]
    assert compared >= 50
    assert certain >= 0.9 * compared  # the compiled choice, not numpy's, was tested
    tri = np.array([[0, 1, 2], [3, 4, 5], [0, 1, 2]])
    pts = np.random.default_rng(1).normal(size=(50, 3))
    best, certain, _ = msac_best(np.ascontiguousarray(pts.T), tri, 0.04)
    if best in (0, 2):
        assert not certain
