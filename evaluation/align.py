"""Two constant rotations that map a ground truth given in frames of its own onto ours.

Public datasets often give motion-capture orientations `R_truth(t)` = R_truthworld_truthbody
in a world frame whose vertical is not z and for a marker body frame rotated against the IMU.
With

    A = R_ourworld_truthworld   (maps truth-world vectors into our z-up world)
    B = R_truthbody_imubody     (maps IMU-body vectors into the truth's body frame)

the truth expressed in our frames is

    R_aligned(t) = A R_truth(t) B        (= R_ourworld_imubody, what an estimate estimates)

and equivalently R_truth(t) = A^-1 R_aligned(t) B^-1. Scoring compares the estimate with
`R_aligned`, so inclination still means the tilt from our world's z and heading the twist
about it.

`estimate_alignment` finds A and B by least squares over all the given samples, minimising
the chordal cost

    J(A, B) = sum_t || A R_truth(t) B - R_est(t) ||_F^2

(Frobenius norm of rotation matrices: for small residuals, 8 sin^2(angle / 2), i.e. about
twice the squared geodesic angle per sample).

1. A closed-form start: with X = B^-1, Y = A the equations read R_est(t) X = Y R_truth(t),
   the rotation part of the robot-world/hand-eye problem "AX = YB" (Zhuang, Roth and
   Sudhakar 1994, IEEE Trans. Robotics and Automation 10(4)). Its Kronecker-product form
   (Shah 2013, "Solving the robot-world/hand-eye calibration problem using the Kronecker
   product", J. Mechanisms and Robotics 5(3)) is linear in vec(X), vec(Y):
   [I (x) R_est(t), -(R_truth(t)^T (x) I)] [vec X; vec Y] = 0; the least-squares null vector is
   the eigenvector of the summed 18 x 18 normal matrix with the smallest eigenvalue, and each
   3 x 3 block is projected onto SO(3) by SVD. This needs no starting guess, so a large
   mounting rotation (90 deg axis swaps) cannot trap the refinement in a local minimum.
2. Alternating least squares on J: with B fixed, ||A R_truth B - R_est|| = ||A - R_est B^-1
   R_truth^-1|| (the norm is invariant under rotations), so the best A is the chordal L2 mean
   of the rotations R_est(t) B^-1 R_truth(t)^-1; with A fixed, the best B is the mean of
   R_truth(t)^-1 A^-1 R_est(t). The mean is the quaternion average of Markley, Cheng,
   Crassidis and Oshman 2007 ("Averaging quaternions", J. Guidance, Control, and Dynamics
   30(4)): the eigenvector of sum_t q_t q_t^T with the largest eigenvalue, which minimises the
   summed squared Frobenius distance of the attitude matrices; SciPy's `Rotation.mean`
   implements it. Each half-step cannot increase J; the loop stops when neither rotation
   moves by more than `tol_rad`.

Observability. The pair is determined only if the truth rotates about at least two
different axes over the recording: for motion about a single fixed axis n, A and B can trade
any rotation about n. Such a recording (and a constant orientation) is rejected. A real
estimator's errors are absorbed where they are constant: a constant heading offset goes into
A's rotation about the vertical, a constant tilt of the estimate into A or B. See README,
"Scoring against truth in other frames (--align)".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

MIN_SAMPLES = 3


@dataclass(frozen=True, eq=False)
class Alignment:
    """The constant rotations between the truth's frames and ours (module docstring).

    world: A = R_ourworld_truthworld.
    body: B = R_truthbody_imubody.
    samples: how many (truth, estimate) pairs they were fitted on.
    iterations: alternating least-squares iterations run.
    """

    world: Rotation
    body: Rotation
    samples: int
    iterations: int

    def apply(self, truth: Rotation) -> Rotation:
        """The truth in our frames: `A R_truth B` (a new `Rotation`; the input is untouched)."""
        return self.world * truth * self.body

    def to_truth_frames(self, estimate: Rotation) -> Rotation:
        """An estimate expressed in the truth's frames: `A^-1 R_est B^-1` (for plots over the truth)."""
        return self.world.inv() * estimate * self.body.inv()

    def to_json(self) -> dict[str, Any]:
        """`world_deg`, `body_deg`: rotation vectors (axis * angle) in degrees; their norms."""
        world, body = self.world.as_rotvec(degrees=True), self.body.as_rotvec(degrees=True)
        return {"world_deg": [float(x) for x in world], "body_deg": [float(x) for x in body],
                "world_angle_deg": float(np.linalg.norm(world)), "body_angle_deg": float(np.linalg.norm(body)),
                "samples": self.samples}


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to `m` (3, 3) in the Frobenius norm (SVD projection)."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def closed_form(r_truth: Rotation, r_est: Rotation) -> tuple[Rotation, Rotation, np.ndarray]:
    """Start values (A, B) from the linear Kronecker-product form (module docstring, step 1).

    Returns A, B and the 18 eigenvalues of the normal matrix divided by the sample count,
    ascending: the second smallest is about 0 when the motion does not determine A and B.
    """
    est, truth = r_est.as_matrix(), r_truth.as_matrix()  # (N, 3, 3)
    eye = np.eye(3)
    # Column-major vec: vec(P X Q) = (Q^T (x) P) vec X (Shah 2013, the rotation equation).
    left = np.einsum("ij,nkl->nikjl", eye, est).reshape(-1, 9, 9)  # I (x) R_est
    right = np.einsum("nji,kl->nikjl", truth, eye).reshape(-1, 9, 9)  # R_truth^T (x) I
    k = np.concatenate([left, -right], axis=2)  # (N, 9, 18)
    normal = np.einsum("nij,nik->jk", k, k) / len(k)
    values, vectors = np.linalg.eigh(normal)
    v = vectors[:, 0]
    x = v[:9].reshape(3, 3, order="F")
    y = v[9:].reshape(3, 3, order="F")
    if np.linalg.det(y) < 0:  # the null vector's sign is arbitrary; rotations have det +1
        x, y = -x, -y
    a = Rotation.from_matrix(_nearest_rotation(y))
    b = Rotation.from_matrix(_nearest_rotation(x)).inv()
    return a, b, values


def estimate_alignment(r_truth: Rotation, r_est: Rotation, tol_rad: float = 1e-10,
                       max_iterations: int = 200) -> Alignment:
    """Least-squares A, B with `A R_truth(t) B ~ R_est(t)` (module docstring).

    r_truth: (N,) truth orientations R_truthworld_truthbody at the estimate's time stamps.
    r_est: (N,) estimated orientations R_ourworld_imubody at the same times.
    Raises ValueError for fewer than 3 pairs or motion that does not determine A and B.
    """
    n = len(r_truth) if not r_truth.single else 1
    if n != (len(r_est) if not r_est.single else 1):
        raise ValueError(f"alignment: {n} truth orientations but {len(r_est)} estimates")
    if n < MIN_SAMPLES:
        raise ValueError(f"alignment needs at least {MIN_SAMPLES} time stamps with both truth and estimate, got {n}")
    a, b, values = closed_form(r_truth, r_est)
    # Exact data with motion about one axis has a 3-dim null space; rich motion a 1-dim one.
    if values[1] <= 1e-9 * values[-1]:
        raise ValueError("alignment is not determined: the truth rotates about a single axis (or not at all) "
                         "over the scored samples, so the world and body rotations can trade a turn about it")
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        a_new = (r_est * b.inv() * r_truth.inv()).mean()  # Markley et al. 2007 average
        b_new = (r_truth.inv() * a_new.inv() * r_est).mean()
        step = max((a_new * a.inv()).magnitude(), (b_new * b.inv()).magnitude())
        a, b = a_new, b_new
        if step < tol_rad:
            break
    return Alignment(a, b, n, iterations)
