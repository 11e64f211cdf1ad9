"""GBA residual terms and their analytic derivatives, vectorized (docs/gba.md).

VC quantities are stored "structure of arrays", tuple index last: a 3D point of every
tuple is (3, T), a Jacobian is (columns, rows, T). Every elementary operation is then a
numpy operation on contiguous length-T rows, and the products with per-image matrices
(rotations, camera-centre derivatives) are single BLAS products per run of tuples that
share an image (tuples sorted by image pair), several times faster than numpy's
batched products of tiny matrices. Classic observations use the same code (transposed).

Derivatives wrt the rotation vector w of ``R = exp([w]x) R0`` use the left Jacobian of
SO(3) (``Poses.Jl``, None at w = 0, where it is the identity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..structs import FloatArray, IndexArray
from .camera import exp_so3, left_jacobian_so3, project_rows
from .problem import GbaOptions, GbaProblem, Parametrization

POSE_SIZE = 6
Segments = tuple[tuple[int, int, int], ...]
"""(start, stop, image) runs of tuples that share an image."""


@dataclass(frozen=True, slots=True)
class RowBlock:
    """Rows ``[start, stop)`` of each VC tuple, one robust-loss block if ``robust``."""

    name: str
    start: int
    stop: int
    robust: bool


def vc_row_blocks(options: GbaOptions) -> tuple[RowBlock, ...]:
    """The row blocks of one VC tuple for these options."""
    blocks = [RowBlock("reproj1", 0, 2, True), RowBlock("reproj2", 2, 4, True)]
    if options.parametrization == Parametrization.SOFT:
        blocks.append(RowBlock("coplanarity", 4, 5, False))
    if options.metric_prior_weight > 0:
        m = blocks[-1].stop
        blocks += [
            RowBlock("depth1", m, m + 1, True),
            RowBlock("depth2", m + 1, m + 2, True),
            RowBlock("thickness", m + 2, m + 5, True),
        ]
    return tuple(blocks)


@dataclass(slots=True)
class Poses:
    """Per-image pose quantities (all (N, ...) float64)."""

    R: FloatArray  # (N, 3, 3)
    t: FloatArray  # (N, 3)
    Jl: (
        FloatArray | None
    )  # (N, 3, 3) left Jacobians of the rotation vectors (None: w = 0)
    centre: FloatArray  # (N, 3) o = -R^T t
    dcentre: FloatArray  # (N, 3, 6) d o / d[w, t]


def make_poses(pose: FloatArray, R0: FloatArray) -> Poses:
    """Poses of (N, 6) [w, t] vectors on reference rotations R0 (N, 3, 3)."""
    w, t = pose[:, :3], pose[:, 3:]
    R = exp_so3(w) @ R0
    Jl = left_jacobian_so3(w) if w.any() else None
    Rt = R.transpose(0, 2, 1)
    dcentre = np.zeros((len(R), 3, POSE_SIZE))
    # o = -R^T t: d o/dw = -R^T [t]x Jl (rows of R^T crossed with t), d o/dt = -R^T.
    dcentre[:, :, :3] = -np.cross(Rt, t[:, None, :])
    if Jl is not None:
        dcentre[:, :, :3] = dcentre[:, :, :3] @ Jl
    dcentre[:, :, 3:] = -Rt
    return Poses(
        R=R, t=t, Jl=Jl, centre=-np.einsum("nij,nj->ni", Rt, t), dcentre=dcentre
    )


@dataclass(slots=True)
class Linearization:
    """Residuals and Jacobian blocks at one x (unweighted by the loss).

    Classic observations row-major; VC tuples with the tuple index last.
    """

    obs_r: FloatArray  # (O, 2)
    vc_r: FloatArray  # (m, T)
    obs_jpose: FloatArray | None = None  # (O, 2, 6) wrt [w, t] of obs_image_idx
    obs_jpoint: FloatArray | None = None  # (O, 2, 3)
    vc_jpose: FloatArray | None = None  # (12, m, T) wrt [pose of image 1 | image 2]
    vc_jvar: FloatArray | None = None  # (k, m, T) wrt the tuple's variables


def image_segments(image_idx: IndexArray) -> Segments:
    """Runs of equal values of ``image_idx``."""
    if len(image_idx) == 0:
        return ()
    bounds = np.flatnonzero(np.diff(image_idx)) + 1
    starts, stops = np.r_[0, bounds], np.r_[bounds, len(image_idx)]
    return tuple(
        (int(a), int(b), int(image_idx[a])) for a, b in zip(starts, stops, strict=True)
    )


def per_image(
    M: FloatArray, idx: IndexArray, X: FloatArray, segs: Segments | None
) -> FloatArray:
    """Y[:, t] = M[idx[t]] @ X[:, t] for (N, p, q) M and (q, T) X: (p, T).

    With ``segs`` (runs of one image, long enough) each run is one BLAS product.
    """
    if segs is None or len(segs) * 32 > X.shape[1]:
        return np.einsum("tpq,qt->pt", M[idx], X)
    out = np.zeros((M.shape[1], X.shape[1]))
    for start, stop, image in segs:
        out[:, start:stop] = M[image] @ X[:, start:stop]
    return out


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b of (3, ...) arrays (first axis)."""
    return np.stack(
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    )


@dataclass(slots=True)
class Projected:
    """Points seen by cameras, with derivatives ((row, column, T) layout)."""

    Xc: FloatArray  # (3, T) camera frame
    xy: FloatArray  # (2, T) pixels
    dX: FloatArray | None = None  # (2, 3, T) d pixel / d X (world)
    dpose: FloatArray | None = None  # (2, 6, T) d pixel / d [w, t]
    dz_dX: FloatArray | None = None  # (3, T) d depth / d X
    dz_dw: FloatArray | None = None  # (3, T) d depth / d w


def project_points(
    X: FloatArray,
    idx: IndexArray,
    poses: Poses,
    intrinsics: FloatArray,
    jac: bool,
    depth: bool = False,
    segs: Segments | None = None,
) -> Projected:
    """Project world points X (3, T) into images idx (T,)."""
    RX = per_image(poses.R, idx, X, segs)
    Xc = RX + np.take(poses.t.T, idx, axis=1)
    xy, dpix = project_rows(Xc, np.take(intrinsics.T, idx, axis=1), with_jacobian=jac)
    if not jac:
        return Projected(Xc=Xc, xy=xy)
    assert dpix is not None
    # d pixel/dX = dpix R; d pixel/dw = dpix (-[R X]x) Jl, row a: (R X) x dpix_a.
    Rt = poses.R.transpose(0, 2, 1)
    dX = np.stack([per_image(Rt, idx, dpix[a], segs) for a in range(2)])
    dpose = np.zeros((2, POSE_SIZE, len(idx)))
    for a in range(2):
        dpose[a, :3] = cross(RX, dpix[a])
        dpose[a, 3:] = dpix[a]
    if poses.Jl is not None:
        JlT = poses.Jl.transpose(0, 2, 1)
        for a in range(2):
            dpose[a, :3] = per_image(JlT, idx, dpose[a, :3], segs)
    out = Projected(Xc=Xc, xy=xy, dX=dX, dpose=dpose)
    if depth:  # row 2 of -[R X]x is (y1, -y0, 0)
        dz_dw = np.stack([RX[1], -RX[0], np.zeros(len(idx))])
        out.dz_dw = (
            dz_dw
            if poses.Jl is None
            else per_image(poses.Jl.transpose(0, 2, 1), idx, dz_dw, segs)
        )
        out.dz_dX = np.take(poses.R[:, 2].T, idx, axis=1)
    return out


def classic_terms(
    points: FloatArray, problem: GbaProblem, poses: Poses, K: FloatArray, jac: bool
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """Classic reprojection residuals (O, 2) and Jacobians (O, 2, 6), (O, 2, 3)."""
    idx = problem.obs_image_idx
    pr = project_points(points[problem.obs_point_idx].T, idx, poses, K, jac)
    r = pr.xy.T - problem.obs_xy
    if not jac:
        return r, None, None
    assert pr.dpose is not None and pr.dX is not None
    return r, pr.dpose.transpose(2, 0, 1), pr.dX.transpose(2, 0, 1)


class _Chain:
    """Accumulates VC Jacobian rows from derivatives wrt X1, X2, o1, o2 ((3, q, T))."""

    def __init__(
        self,
        m: int,
        k: int,
        hard: bool,
        ab: FloatArray | None,
        u: FloatArray,
        v: FloatArray,
        poses: Poses,
        i1: IndexArray,
        i2: IndexArray,
        segs: tuple[Segments | None, Segments | None],
    ) -> None:
        num = len(i1)
        self.jpose = np.zeros((2 * POSE_SIZE, m, num))
        self.jvar = np.zeros((k, m, num))
        self.hard, self.ab, self.u, self.v = hard, ab, u, v
        self.dcT = poses.dcentre.transpose(0, 2, 1)  # (N, 6, 3)
        self.idx, self.segs = (i1, i2), segs

    def centre(self, which: int, rows: slice, do: FloatArray) -> None:
        """Chain d/do (3, q, T) of the centre of image 1 (0) or 2 (1) to its pose."""
        cols = slice(6 * which, 6 * which + 6)
        for q, row in enumerate(range(rows.start, rows.stop)):
            self.jpose[cols, row] += per_image(
                self.dcT, self.idx[which], do[:, q], self.segs[which]
            )

    def add(
        self,
        rows: slice,
        *,
        dX1: FloatArray | None = None,
        dX2: FloatArray | None = None,
        do1: FloatArray | None = None,
        do2: FloatArray | None = None,
        skip_o2: bool = False,
    ) -> None:
        """Add derivatives of rows wrt X1, X2 (world), o1 and o2, each (3, q, T).

        ``skip_o2``: the caller adds the o2 part of X2 (hard) itself.
        """
        if dX2 is not None and self.hard:
            # X2 = (1 + a) X1 - (a + b) o1 + b o2 with a, b variables.
            assert self.ab is not None
            a, b = self.ab
            self.jvar[3, rows] += np.einsum("iqt,it->qt", dX2, self.u)
            self.jvar[4, rows] += np.einsum("iqt,it->qt", dX2, self.v)
            dX1 = (1.0 + a) * dX2 if dX1 is None else dX1 + (1.0 + a) * dX2
            do1 = -(a + b) * dX2 if do1 is None else do1 - (a + b) * dX2
            if not skip_o2:
                do2 = b * dX2 if do2 is None else do2 + b * dX2
        elif dX2 is not None:
            self.jvar[3:6, rows] += dX2
        if dX1 is not None:
            self.jvar[0:3, rows] += dX1
        if do1 is not None:
            self.centre(0, rows, do1)
        if do2 is not None:
            self.centre(1, rows, do2)


def vc_terms(
    tup: FloatArray,
    problem: GbaProblem,
    options: GbaOptions,
    poses: Poses,
    K: FloatArray,
    jac: bool,
    segments: tuple[Segments, Segments] | None = None,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """VC rows (m, T), their derivatives wrt [pose1 | pose2] (12, m, T) and the tuple
    variables (k, m, T); ``tup`` (k, T) are the tuple variables.

    Each row block gives derivatives wrt X1, X2, the centres o1, o2 and the direct
    pose terms; :class:`_Chain` maps them to the variables (X2 and the centres depend
    on them), block by block.
    """
    hard = options.parametrization == Parametrization.HARD
    blocks = {b.name: b for b in vc_row_blocks(options)}
    m = max(b.stop for b in blocks.values())
    i1, i2 = problem.vc_image_idx1, problem.vc_image_idx2
    o1, o2 = np.take(poses.centre.T, i1, axis=1), np.take(poses.centre.T, i2, axis=1)
    x1 = tup[0:3]
    u, v = x1 - o1, o2 - o1
    ab = tup[3:5] if hard else None  # (2, T) thickness a, b
    x2 = x1 + ab[0] * u + ab[1] * v if ab is not None else tup[3:6]
    r = np.zeros((m, len(i1)))
    seg1, seg2 = segments if segments is not None else (None, None)
    depth = "depth1" in blocks
    p1 = project_points(x1, i1, poses, K, jac, depth, seg1)
    p2 = project_points(x2, i2, poses, K, jac, depth, seg2)
    r[0:2] = p1.xy - problem.vc_xy1.T
    r[2:4] = p2.xy - problem.vc_xy2.T
    chain = None
    if jac:
        assert p1.dX is not None and p1.dpose is not None
        assert p2.dX is not None and p2.dpose is not None
        chain = _Chain(
            m,
            5 if hard else 6,
            hard,
            ab,
            u,
            v,
            poses,
            i1,
            i2,
            (seg1, seg2),
        )
        chain.jpose[0:6, 0:2] = p1.dpose.transpose(1, 0, 2)
        chain.jpose[6:12, 2:4] = p2.dpose.transpose(1, 0, 2)
        chain.add(slice(0, 2), dX1=p1.dX.transpose(1, 0, 2))
        if ab is not None:
            b = ab[1]
            # The o2 part of X2 (b o2) in closed form: with dX2 = dpix R2 and
            # d o2 = -R2^T [[t2]x Jl2 | I], b dX2 d o2 = b [t2 x dpix (Jl2) | -dpix].
            chain.add(slice(2, 4), dX2=p2.dX.transpose(1, 0, 2), skip_o2=True)
            t2 = np.take(poses.t.T, i2, axis=1)
            for q in range(2):
                dpix = p2.dpose[q, 3:]
                rot = b * cross(t2, dpix)
                if poses.Jl is not None:
                    rot = per_image(poses.Jl.transpose(0, 2, 1), i2, rot, seg2)
                chain.jpose[6:9, 2 + q] += rot
                chain.jpose[9:12, 2 + q] *= 1.0 - b
        else:
            chain.add(slice(2, 4), dX2=p2.dX.transpose(1, 0, 2))
    if "coplanarity" in blocks:
        row = blocks["coplanarity"].start
        # Distance of X2 to the plane (o1, X1, o2), as an angle seen from camera 2
        # times its focal length: about the pixel distance to the epipolar line.
        focal = 0.5 * (K[i2, 0] + K[i2, 1])
        kw = options.coplanarity_weight * focal
        q_ = x2 - x1
        mvec = cross(u, v)
        mn = np.maximum(np.sqrt((mvec * mvec).sum(0)), 1e-300)
        n = mvec / mn
        h = (q_ * n).sum(0)
        lvec = x2 - o2
        ell = np.sqrt((lvec * lvec).sum(0))
        r[row] = kw * h / ell
        if chain is not None:
            gm = (q_ - n * h) / mn  # d h / d(u x v)
            vg, gu = cross(v, gm), cross(gm, u)
            c = kw / ell
            cl = (kw * h / ell**3) * lvec
            chain.add(
                slice(row, row + 1),
                dX1=(c * (vg - n))[:, None],
                dX2=(c * n - cl)[:, None],
                do1=(-c * (vg + gu))[:, None],
                do2=(c * gu + cl)[:, None],
            )
    if depth:
        row = blocks["depth1"].start
        has = problem.vc_has_prior
        z1 = np.where(has, problem.vc_prior_depth1, 1.0)
        z2 = np.where(has, problem.vc_prior_depth2, 1.0)
        c1 = np.where(has, options.metric_prior_weight / z1, 0.0)
        c2 = np.where(has, options.metric_prior_weight / z2, 0.0)
        r[row] = c1 * (p1.Xc[2] - z1)
        r[row + 1] = c2 * (p2.Xc[2] - z2)
        a0 = np.where(has, problem.vc_prior_a, 0.0)
        b0 = np.where(has, problem.vc_prior_b, 0.0)
        r[row + 2 : row + 5] = c1 * (x2 - x1 - a0 * u - b0 * v)
        if chain is not None:
            assert p1.dz_dX is not None and p1.dz_dw is not None
            assert p2.dz_dX is not None and p2.dz_dw is not None
            chain.add(slice(row, row + 1), dX1=(c1 * p1.dz_dX)[:, None])
            chain.jpose[0:3, row] += c1 * p1.dz_dw
            chain.jpose[5, row] += c1
            chain.add(slice(row + 1, row + 2), dX2=(c2 * p2.dz_dX)[:, None])
            chain.jpose[6:9, row + 1] += c2 * p2.dz_dw
            chain.jpose[11, row + 1] += c2
            eye = np.eye(3)[:, :, None]
            chain.add(
                slice(row + 2, row + 5),
                dX1=-(c1 * (1.0 + a0)) * eye,
                dX2=c1 * eye,
                do1=(c1 * (a0 + b0)) * eye,
                do2=-(c1 * b0) * eye,
            )
    if chain is None:
        return r, None, None
    return r, chain.jpose, chain.jvar
