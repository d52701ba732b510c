"""The compiled kernels (softbody.kernels, numba) against their numpy references and against independent truth."""
import numpy as np
import pytest

from softbody import kernels, rotation


def _numpy_path(monkeypatch):
    monkeypatch.setattr(kernels, "ENABLED", False)


@pytest.mark.skipif(not kernels.ENABLED, reason="numba not installed")
def test_polar_kernel_equals_the_numpy_iteration_and_the_svd(monkeypatch):
    """Random well-shaped, inverted and degenerate F: the compiled rotations equal the numpy iteration's to its
    tolerance, are proper rotations, and equal U V^T of the SVD for every F with det F > 0."""
    rng = np.random.default_rng(7)
    n = 3000
    F = np.eye(3) + 0.6 * rng.standard_normal((n, 3, 3))
    F[:50, :, 0] *= -1.0  # inverted
    F[50:60, 2] = F[50:60, 0]  # degenerate: two equal rows
    F9 = np.ascontiguousarray(F.reshape(n, 9).T)
    R = rotation.polar_rotation_components(F9)
    with monkeypatch.context() as m:
        _numpy_path(m)
        R0 = rotation.polar_rotation_components(F9)
    assert np.abs(R - R0).max() < 1e-11
    Rm = R.T.reshape(n, 3, 3)
    assert np.abs(Rm @ np.swapaxes(Rm, 1, 2) - np.eye(3)).max() < 1e-12
    assert np.all(np.linalg.det(Rm) > 0.999999)
    good = np.linalg.det(F) > 1e-3
    U, _, Vt = np.linalg.svd(F[good])
    assert np.abs(Rm[good] - U @ Vt).max() < 1e-9
