"""Residuals that make the cameras agree on "up": one measured direction per camera.

Each camera i measured the direction of gravity in its own frame, g_i (from the
scene's vertical lines, :mod:`colmap_vc.gravity`). The world's up u is one unit
vector (a parameter block on the sphere), and camera i, rotated by R_i (its
cam_from_world), should see it as g_i: the residual is R_i u - g_i, whose length is
the angle between them. It is weighed against the reprojection residuals in
pixels: divided by the direction's standard error and multiplied by the
keypoints' pixel noise, it is in the same units as a reprojection error of that
noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyceres

from ..structs import FloatArray, IndexArray


@dataclass(frozen=True, kw_only=True, slots=True)
class UpPriors:
    """Measured up directions of some images (their cameras' frames)."""

    image_id: IndexArray  # (I,) int64
    up_cam: FloatArray  # (I, 3) unit vectors
    sigma_rad: FloatArray  # (I,) standard error of each direction
    pixel_noise_px: float  # the reprojection noise the angles are weighed against
    robust_sigmas: float = 2.0  # scale of the Cauchy loss, in standard errors

    def __post_init__(self) -> None:
        n = self.image_id.shape[0]
        if self.up_cam.shape != (n, 3) or self.sigma_rad.shape != (n,):
            raise ValueError(
                f"UpPriors: {n} images, up_cam {self.up_cam.shape}, "
                f"sigma_rad {self.sigma_rad.shape}"
            )
        if not np.all(self.sigma_rad > 0) or not self.pixel_noise_px > 0:
            raise ValueError("UpPriors: noises must be positive")


def rotate_with_jacobian(q: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """R(q) u and its derivative (3, 4) with respect to q = (x, y, z, w), a unit
    quaternion (Eigen's order, as COLMAP stores it):
    R u = u + 2 w (v x u) + 2 v x (v x u), v = (x, y, z)."""
    v, w = q[:3], q[3]
    vxu = np.cross(v, u)
    Ru = u + 2.0 * w * vxu + 2.0 * np.cross(v, vxu)
    skew_u = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    J = np.empty((3, 4))
    J[:, :3] = -2.0 * w * skew_u + 2.0 * (
        (v @ u) * np.eye(3) + np.outer(v, u) - 2.0 * np.outer(u, v)
    )
    J[:, 3] = 2.0 * vxu
    return Ru, J


def rotation_matrix(q: FloatArray) -> FloatArray:
    """(3, 3) R(q) of a unit quaternion q = (x, y, z, w): its image of each axis."""
    return np.column_stack([rotate_with_jacobian(q, e)[0] for e in np.eye(3)])


class UpCost(pyceres.CostFunction):
    """(R(q) u - g) * scale on a COLMAP pose block [qx qy qz qw tx ty tz] and u."""

    def __init__(self, up_cam: FloatArray, scale: float) -> None:
        super().__init__()
        self.up_cam = np.asarray(up_cam, dtype=np.float64)
        self.scale = float(scale)
        self.set_num_residuals(3)
        self.set_parameter_block_sizes([7, 3])

    def Evaluate(
        self,
        parameters: list[np.ndarray],
        residuals: np.ndarray,
        jacobians: list[np.ndarray | None] | None,
    ) -> bool:
        pose, u = np.asarray(parameters[0]), np.asarray(parameters[1])
        Ru, dq = rotate_with_jacobian(pose[:4], u)
        residuals[:] = (Ru - self.up_cam) * self.scale
        if jacobians is not None:
            if jacobians[0] is not None:
                J = np.zeros((3, 7))
                J[:, :4] = dq * self.scale
                jacobians[0][:] = J.ravel()
            if jacobians[1] is not None:
                jacobians[1][:] = (rotation_matrix(pose[:4]) * self.scale).ravel()
        return True


def add_up_priors(
    problem: pyceres.Problem, pose_blocks: dict[int, np.ndarray], priors: UpPriors
) -> tuple[np.ndarray, list]:
    """Add the world's up (a block on the sphere, started at the mean of the
    measurements turned into the world) and one residual per image whose pose is
    in ``pose_blocks``, with a Cauchy loss at ``robust_sigmas`` standard errors (a
    wrong vanishing point is an outlier). Returns the up block and the objects
    the problem needs alive until the solve is over (the manifold too: Ceres
    does not own it, and a freed one crashes the solve)."""
    rows = [k for k, i in enumerate(priors.image_id.tolist()) if i in pose_blocks]
    world = []
    for k in rows:  # loop over the measured cameras
        R = rotation_matrix(pose_blocks[int(priors.image_id[k])][:4])
        world.append(R.T @ priors.up_cam[k])
    up = np.mean(world, axis=0) if world else np.array([0.0, 0.0, 1.0])
    up /= np.linalg.norm(up)
    problem.add_parameter_block(up, 3)
    sphere = pyceres.SphereManifold(3)
    problem.set_manifold(up, sphere)
    loss = pyceres.CauchyLoss(priors.robust_sigmas * priors.pixel_noise_px)
    alive: list = [sphere, loss]
    for k in rows:  # loop over the measured cameras
        scale = priors.pixel_noise_px / float(priors.sigma_rad[k])
        cost = UpCost(priors.up_cam[k], scale)
        problem.add_residual_block(
            cost, loss, [pose_blocks[int(priors.image_id[k])], up]
        )
        alive.append(cost)
    return up, alive
