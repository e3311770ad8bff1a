"""The bundle window with its points eliminated (mapping.bundle_reduced.ReducedProblem): the
dense per-observation point blocks (WindowProblem.point_terms) are the full sparse Jacobian's
point columns, the camera-side build (points=False) is its other columns, and the reduced
Jacobian is the Schur projection J_θ - J_X H⁻¹ J_Xᵀ W J_θ written with the full sparse matrix,
on a window of a seeded synthetic drive with every factor on, global and rolling shutter."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from roadsurf.mapping.bundle_problem import WindowProblem
from roadsurf.mapping.bundle_reduced import ReducedProblem
from roadsurf.mapping.pose_graph import _robust_weights
from tests.mapping.bundle_synth import recorded_window


@pytest.fixture(scope="module", params=[0.0, 0.03], ids=["global", "rolling"])
def problem(request: pytest.FixtureRequest) -> WindowProblem:
    return recorded_window(5, request.param)


def _x(problem: WindowProblem) -> np.ndarray:
    return 1e-4 * np.random.default_rng(1).standard_normal(problem.n)


def test_point_blocks_and_camera_columns_are_the_full_jacobians(problem: WindowProblem) -> None:
    x = _x(problem)
    r, J = problem._build(x)
    r_cam, J_cam = problem._build(x, points=False)
    assert np.array_equal(r, r_cam)
    nt = problem.point_col0
    assert J_cam.shape == (J.shape[0], nt)
    assert abs(J_cam - J[:, :nt]).max() == 0.0
    ot = problem.point_terms(x)
    m = len(problem.d.obs_p)
    assert np.array_equal(np.concatenate(ot.res), r[: 3 * m])
    Jx = J[: 3 * m, nt:].toarray()
    dense = np.zeros_like(Jx)
    cols = 3 * np.tile(problem.d.obs_p, 3)[:, None] + np.arange(3)
    np.put_along_axis(dense, cols, np.concatenate(ot.Ax), axis=1)
    assert np.allclose(dense, Jx, rtol=1e-12, atol=1e-12 * np.abs(Jx).max())
    assert abs(J[3 * m :, nt:]).max() == 0.0  # the points appear in the observation rows only


def test_the_reduced_jacobian_is_the_schur_projection(problem: WindowProblem) -> None:
    red = ReducedProblem(problem, "cauchy", 1.0)
    theta = _x(problem)[: red.n]
    Jr = red.jac(theta).toarray()
    # the reference, from the full sparse Jacobian at the points the reduction settled on
    r, J = problem._build(red.full_x(theta))
    nt = red.n
    Jt, Jx = J[:, :nt].toarray(), J[:, nt:].toarray()
    w = _robust_weights(r, "cauchy", 1.0)
    H = Jx.T @ (w[:, None] * Jx)
    P = len(red.dX) // 3
    for p in range(P):  # block-diagonal per point, as the reduction's H (+ its ridge)
        H[3 * p : 3 * p + 3, 3 * p : 3 * p + 3] += 1e-9 * np.eye(3)
    ref = Jt - Jx @ np.linalg.solve(H, Jx.T @ (w[:, None] * Jt))
    assert np.allclose(Jr, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    assert np.array_equal(red.fun(theta), r)
    assert sp.issparse(red.jac(theta))


def test_the_factored_products_are_the_explicit_matrixs(problem: WindowProblem) -> None:
    red = ReducedProblem(problem, "cauchy", 1.0)
    theta = _x(problem)[: red.n]
    op, J = red.jac_op(theta), red.jac(theta)
    rng = np.random.default_rng(2)
    v, u = rng.standard_normal(J.shape[1]), rng.standard_normal(J.shape[0])
    assert np.allclose(op.matvec(v), J @ v, rtol=1e-10, atol=1e-10 * np.abs(J @ v).max())
    assert np.allclose(op.rmatvec(u), J.T @ u, rtol=1e-10, atol=1e-10 * np.abs(J.T @ u).max())
