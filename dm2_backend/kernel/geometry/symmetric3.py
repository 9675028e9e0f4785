"""The eigenvalues and the smallest eigenvector of many symmetric 3x3 matrices at once (a plane's normal and
flatness from its points' scatter), in closed form: several times faster than ``numpy.linalg.eigh``'s loop over
LAPACK calls, to the same accuracy where the smallest eigenvalue stands apart.

The eigenvalues come from the characteristic cubic (trigonometric form, Smith 1961); the eigenvector from the
largest cross product of two rows of ``A - lambda_0 I``, which all lie across it. The cubic's roots lose
precision where two of them nearly coincide, and with them the vector: a matrix whose vector's residual
``|A v - lambda_0 v|`` is not ``ACCURACY`` times smaller than the gap between the two smallest eigenvalues (which
bounds the vector's error), or whose eigenvalues are not finite (a zero matrix), is handed to ``numpy.linalg.eigh``;
so is one whose two smallest eigenvalues are closer than ``DEGENERATE`` of the largest (no normal stands out: a
line, a point), where any vector across is as right and ``eigh``'s choice is kept.
"""

from __future__ import annotations

import numpy as np

#: the largest error (radians) of a vector kept from the closed form: its residual over the eigenvalue gap
ACCURACY = 1e-12
#: the two smallest eigenvalues closer than this share of the largest: a degenerate matrix
DEGENERATE = 1e-6


def smallest_eigen(a00: np.ndarray, a01: np.ndarray, a02: np.ndarray, a11: np.ndarray, a12: np.ndarray,
                   a22: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (n,3), ascending, and the unit eigenvector of the smallest (n,3) of the symmetric matrices with
    upper entries ``a00 .. a22`` (each (n,)). The vector's sign is arbitrary, as ``eigh``'s."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.arccos(np.clip(det / (2.0 * p**3), -1.0, 1.0)) / 3.0
    lam = np.empty((len(q), 3))
    lam[:, 2] = q + 2.0 * p * np.cos(phi)
    lam[:, 0] = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    lam[:, 1] = 3.0 * q - lam[:, 2] - lam[:, 0]
    c00, c11, c22 = a00 - lam[:, 0], a11 - lam[:, 0], a22 - lam[:, 0]
    cross = np.empty((3, 3, len(q)))  # rows r0 x r1, r0 x r2, r1 x r2 of A - lambda_0 I
    cross[0] = a01 * a12 - a02 * c11, a02 * a01 - c00 * a12, c00 * c11 - a01 * a01
    cross[1] = a01 * c22 - a02 * a12, a02 * a02 - c00 * c22, c00 * a12 - a01 * a02
    cross[2] = c11 * c22 - a12 * a12, a12 * a02 - a01 * c22, a01 * a12 - c11 * a02
    norm2 = np.einsum("kin,kin->kn", cross, cross)
    best = norm2.argmax(0)
    rows = np.arange(len(q))
    with np.errstate(invalid="ignore", divide="ignore"):
        vec = cross[best, :, rows] / np.sqrt(norm2[best, rows])[:, None]
    x, y, z = vec[:, 0], vec[:, 1], vec[:, 2]
    Av = (a00 * x + a01 * y + a02 * z, a01 * x + a11 * y + a12 * z, a02 * x + a12 * y + a22 * z)
    lam[:, 0] = Av[0] * x + Av[1] * y + Av[2] * z  # the Rayleigh quotient: exact to the vector's error squared
    lam[:, 1], lam[:, 2] = _across(a00, a01, a02, a11, a12, a22, x, y, z)
    with np.errstate(invalid="ignore"):
        residual = np.sqrt((Av[0] - lam[:, 0] * x) ** 2 + (Av[1] - lam[:, 0] * y) ** 2 + (Av[2] - lam[:, 0] * z) ** 2)
        gap = lam[:, 1] - lam[:, 0]
        hard = ~((residual <= ACCURACY * gap) & (gap > DEGENERATE * np.abs(lam[:, 2])))
    if hard.any():
        A = np.stack([a00[hard], a01[hard], a02[hard], a01[hard], a11[hard], a12[hard], a02[hard], a12[hard],
                      a22[hard]], 1).reshape(-1, 3, 3)
        lam[hard], vectors = np.linalg.eigh(A)
        vec[hard] = vectors[:, :, 0]
    return lam, vec


def _across(a00, a01, a02, a11, a12, a22, x, y, z) -> tuple[np.ndarray, np.ndarray]:
    """The two eigenvalues of the matrices across their unit vectors (x, y, z): those of the 2x2 matrix the plane
    across the vector sees, from the quadratic's stable form (the cubic's lose precision where they nearly
    coincide: a round patch)."""
    # e1: across (x, y, z) from its two largest components (never a short vector to normalise); e2 = v x e1
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    small_x, small_y = (ax <= ay) & (ax <= az), (ay < ax) & (ay <= az)
    e1 = (np.where(small_x, 0.0, np.where(small_y, z, -y)), np.where(small_x, -z, np.where(small_y, 0.0, x)),
          np.where(small_x, y, np.where(small_y, -x, 0.0)))
    norm = np.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        e1 = (e1[0] / norm, e1[1] / norm, e1[2] / norm)
    e2 = (y * e1[2] - z * e1[1], z * e1[0] - x * e1[2], x * e1[1] - y * e1[0])

    def form(u, v):
        return (u[0] * (a00 * v[0] + a01 * v[1] + a02 * v[2]) + u[1] * (a01 * v[0] + a11 * v[1] + a12 * v[2])
                + u[2] * (a02 * v[0] + a12 * v[1] + a22 * v[2]))

    b11, b12, b22 = form(e1, e1), form(e1, e2), form(e2, e2)
    mid, half = 0.5 * (b11 + b22), np.hypot(0.5 * (b11 - b22), b12)
    return mid - half, mid + half
