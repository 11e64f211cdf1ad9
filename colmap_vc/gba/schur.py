"""The linear algebra of one LM step: normal equations and the Schur complement.

Every point block is eliminated: classic points (3 unknowns, shared by several
observations: 3 x 3 inverses and the pose fill-in of all observation pairs) and VC
tuples (5 or 6 unknowns each, one residual group each). VC arrays keep the tuple
index last (see terms.py): the per-tuple k x k Cholesky factorizations run as Python
loops over the k x k entries on contiguous length-T rows, and the per-pair sums are
BLAS products over the (contiguous) tuples of each image pair. The reduced pose
system (6 per image) is dense and solved by Cholesky, like Ceres' DENSE_SCHUR.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

from ..structs import FloatArray, IndexArray
from .model import POSE_SIZE, Layout, Linearization
from .problem import GbaProblem

MIN_DIAGONAL, MAX_DIAGONAL = 1e-6, 1e32  # Ceres' min/max_lm_diagonal


def cholesky_soa(A: FloatArray) -> FloatArray:
    """Lower Cholesky factors of SPD matrices stored (k, k, T) (one row per entry).

    Vectorized over T with the k x k loops in Python on contiguous (T,) rows, which is
    faster than numpy's per-matrix LAPACK calls for k <= 6; pivots are clamped > 0.
    """
    k = A.shape[0]
    L = np.zeros_like(A)
    for j in range(k):
        d = A[j, j].copy()
        for p in range(j):
            d -= L[j, p] * L[j, p]
        L[j, j] = np.sqrt(np.maximum(d, 1e-300))
        inv = 1.0 / L[j, j]
        for i in range(j + 1, k):
            e = A[i, j].copy()
            for p in range(j):
                e -= L[i, p] * L[j, p]
            L[i, j] = e * inv
    return L


def forward_soa(L: FloatArray, B: FloatArray) -> FloatArray:
    """Solve L X = B for L (k, k, T) lower and B (k, c, T)."""
    X = np.zeros_like(B)
    for i in range(L.shape[0]):
        acc = B[i].copy()
        for j in range(i):
            acc -= L[i, j] * X[j]
        X[i] = acc / L[i, i]
    return X


def backward_soa(L: FloatArray, y: FloatArray) -> FloatArray:
    """Solve L^T x = y for L (k, k, T) lower and y (k, T)."""
    k = L.shape[0]
    x = np.zeros_like(y)
    for i in range(k - 1, -1, -1):
        acc = y[i].copy()
        for j in range(i + 1, k):
            acc -= L[j, i] * x[j]
        x[i] = acc / L[i, i]
    return x


def _damped(V: FloatArray, diag: FloatArray, lam: float) -> FloatArray:
    out = V.copy()
    idx = np.arange(V.shape[-1])
    out[:, idx, idx] += lam * diag
    return out


def _indicator(groups: IndexArray, num_groups: int) -> scipy.sparse.csr_matrix:
    """(G, len(groups)) 0/1 matrix that sums rows by group."""
    n = len(groups)
    return scipy.sparse.csr_matrix(
        (np.ones(n), (groups, np.arange(n))), shape=(num_groups, n)
    )


class Schur:
    """Fixed structure of one problem: aggregation matrices and pair segments.

    The VC tuples must be sorted by image pair.
    """

    def __init__(self, problem: GbaProblem, lay: Layout) -> None:
        n = problem.num_images
        self.n = n
        self.free = np.zeros(POSE_SIZE * n, bool)
        self.free[
            (POSE_SIZE * np.arange(n)[:, None] + np.arange(POSE_SIZE))[
                lay.pose_col >= 0
            ]
        ] = True
        self.full_of_col = (POSE_SIZE * np.arange(n)[:, None] + np.arange(POSE_SIZE))[
            lay.pose_col >= 0
        ]
        order = np.argsort(lay.pose_col[lay.pose_col >= 0])
        self.full_of_col = self.full_of_col[order]  # x column -> full pose index
        img = problem.obs_image_idx
        self.obs_image, self.obs_point = img, problem.obs_point_idx
        self.vc_image1, self.vc_image2 = problem.vc_image_idx1, problem.vc_image_idx2
        self.obs_by_image = _indicator(img, n)
        self.refine_points = lay.num_points > 0
        if self.refine_points:
            pt = problem.obs_point_idx
            self.obs_by_point = _indicator(pt, problem.num_points)
            # All ordered pairs of observations of one point (the Schur fill-in).
            order = np.argsort(pt, kind="stable")
            counts = np.bincount(pt, minlength=problem.num_points)
            starts = np.cumsum(counts) - counts
            per_obs = counts[pt]
            e1 = np.repeat(np.arange(len(pt)), per_obs)
            offset = np.arange(len(e1)) - np.repeat(
                np.cumsum(per_obs) - per_obs, per_obs
            )
            e2 = order[starts[pt[e1]] + offset]
            self.pair_e1, self.pair_e2 = e1, e2
            self.pair_sum = _indicator(img[e1] * n + img[e2], n * n)
        key = problem.vc_image_idx1 * n + problem.vc_image_idx2
        if len(key) and (np.diff(key) < 0).any():
            raise ValueError("VC tuples must be sorted by image pair for the LM solver")
        bounds = np.flatnonzero(np.diff(key)) + 1
        self.seg_start = np.r_[0, bounds] if len(key) else np.zeros(0, np.int64)
        self.seg_stop = np.r_[bounds, len(key)] if len(key) else np.zeros(0, np.int64)
        self.seg_pair = [
            (int(problem.vc_image_idx1[s]), int(problem.vc_image_idx2[s]))
            for s in self.seg_start
        ]
        # Rows/columns of S (and rhs) of each pair's 12 x 12 block (and 12 vector).
        full = np.array(
            [
                np.r_[
                    POSE_SIZE * a + np.arange(POSE_SIZE),
                    POSE_SIZE * b + np.arange(POSE_SIZE),
                ]
                for a, b in self.seg_pair
            ],
            np.int64,
        ).reshape(-1, 2 * POSE_SIZE)
        self.pair_rows = np.repeat(full, 2 * POSE_SIZE, axis=1)
        self.pair_cols = np.tile(full, (1, 2 * POSE_SIZE))
        self.pair_vec_rows = full
        self.segments = (
            tuple(
                (int(s), int(e), a)
                for (a, _), s, e in zip(
                    self.seg_pair, self.seg_start, self.seg_stop, strict=True
                )
            ),
            tuple(
                (int(s), int(e), b)
                for (_, b), s, e in zip(
                    self.seg_pair, self.seg_start, self.seg_stop, strict=True
                )
            ),
        )

    def blocks(self, i: int) -> slice:
        return slice(POSE_SIZE * i, POSE_SIZE * (i + 1))


@dataclass(slots=True)
class System:
    """Normal equations of one linearization (before damping), loss-weighted.

    VC arrays keep the tuple index last (see terms.py).
    """

    U: FloatArray  # (6N, 6N) pose block (classic and VC terms)
    g: FloatArray  # (6N,) pose gradient
    obs_W: FloatArray | None  # (O, 6, 3)
    Vp: FloatArray | None  # (P, 3, 3)
    gp: FloatArray | None  # (P, 3)
    r: FloatArray  # (m, T) weighted VC residuals
    Jpose: FloatArray  # (12, m, T) weighted
    Jv: FloatArray  # (k, m, T) weighted
    V: FloatArray  # (k, k, T) Jv^T Jv per tuple
    gv: FloatArray  # (k, T) Jv^T r per tuple


def _pair_sums(
    st: Schur,
    left: FloatArray,
    right: FloatArray,
    vec: FloatArray | None,
) -> tuple[FloatArray, FloatArray]:
    """Per image pair: sum_t left_t^T right_t (12, 12) and sum_t left_t^T vec_t (12,).

    ``left``/``right`` (12, q, T), ``vec`` (q, T); the tuples of a pair are one
    contiguous run, so each row q of a pair is one BLAS product.
    """
    num = len(st.seg_pair)
    H = np.zeros((num, 2 * POSE_SIZE, 2 * POSE_SIZE))
    G = np.zeros((num, 2 * POSE_SIZE))
    for k, (s, e) in enumerate(zip(st.seg_start, st.seg_stop, strict=True)):
        for q in range(left.shape[1]):
            H[k] += left[:, q, s:e] @ right[:, q, s:e].T
            if vec is not None:
                G[k] += left[:, q, s:e] @ vec[q, s:e]
    return H, G


def _scatter_pairs(
    st: Schur,
    S: FloatArray,
    rhs: FloatArray | None,
    H: FloatArray,
    G: FloatArray | None,
) -> None:
    """Add the pairs' (12, 12) blocks to S and (12,) blocks to rhs."""
    if len(H):
        np.add.at(S, (st.pair_rows, st.pair_cols), H.reshape(len(H), -1))
        if rhs is not None and G is not None:
            np.add.at(rhs, st.pair_vec_rows, G)


def _eliminated_pairs(
    st: Schur,
    B: FloatArray,
    Jpose: FloatArray,
    Br: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Per pair: -sum_t Z_t^T Z_t (12, 12) and sum_t Z_t^T (B r)_t (12,), Z = B Jpose.

    Z is formed one pair at a time (it stays in cache) instead of for all tuples.
    """
    num, (k, m, _) = len(st.seg_pair), B.shape
    H = np.zeros((num, 2 * POSE_SIZE, 2 * POSE_SIZE))
    G = np.zeros((num, 2 * POSE_SIZE))
    for p, (s, e) in enumerate(zip(st.seg_start, st.seg_stop, strict=True)):
        J = Jpose[:, :, s:e]
        for i in range(k):
            Zi = B[i, 0, s:e] * J[:, 0]
            for q in range(1, m):
                Zi += B[i, q, s:e] * J[:, q]
            H[p] -= Zi @ Zi.T
            G[p] += Zi @ Br[i, s:e]
    return H, G


def normal_equations(
    lin: Linearization, w_obs: FloatArray, w_vc: FloatArray, st: Schur
) -> System:
    assert lin.obs_jpose is not None and lin.obs_jpoint is not None
    assert lin.vc_jpose is not None and lin.vc_jvar is not None
    n6 = POSE_SIZE * st.n
    U, g = np.zeros((n6, n6)), np.zeros(n6)
    r = lin.obs_r * w_obs[:, None]
    Jc = lin.obs_jpose * w_obs[:, None, None]
    JcT = Jc.transpose(0, 2, 1)
    diag = (st.obs_by_image @ (JcT @ Jc).reshape(-1, 36)).reshape(-1, 6, 6)
    gc = st.obs_by_image @ np.einsum("oji,oj->oi", Jc, r)
    for i in range(st.n):
        U[st.blocks(i), st.blocks(i)] += diag[i]
        g[st.blocks(i)] += gc[i]
    obs_W = Vp = gp = None
    if st.refine_points:
        Jp = lin.obs_jpoint * w_obs[:, None, None]
        JpT = Jp.transpose(0, 2, 1)
        Vp = (st.obs_by_point @ (JpT @ Jp).reshape(-1, 9)).reshape(-1, 3, 3)
        gp = st.obs_by_point @ np.einsum("oji,oj->oi", Jp, r)
        obs_W = JcT @ Jp
    # VC terms, weighted in place (the linearization is not used after this).
    rv = lin.vc_r * w_vc
    Jpose, Jv = lin.vc_jpose, lin.vc_jvar
    Jpose *= w_vc
    Jv *= w_vc
    H, G = _pair_sums(st, Jpose, Jpose, rv)
    _scatter_pairs(st, U, g, H, G)
    k = len(Jv)
    V = np.zeros((k, k, rv.shape[1]))
    for i in range(k):  # V = Jv^T Jv, symmetric
        for j in range(i + 1):
            V[i, j] = V[j, i] = (Jv[i] * Jv[j]).sum(0)
    return System(
        U=U,
        g=g,
        obs_W=obs_W,
        Vp=Vp,
        gp=gp,
        r=rv,
        Jpose=Jpose,
        Jv=Jv,
        V=V,
        gv=(Jv * rv).sum(1),
    )


def _diag(V: FloatArray) -> FloatArray:
    return np.clip(np.diagonal(V, axis1=-2, axis2=-1), MIN_DIAGONAL, MAX_DIAGONAL)


def damped_step(
    sys: System, st: Schur, lam: float
) -> tuple[FloatArray, FloatArray, FloatArray | None, float]:
    """Damped Gauss-Newton step: poses (6N,), tuples (k, T), points (P, 3), and the
    decrease of the linear model."""
    Dc = np.clip(np.diagonal(sys.U), MIN_DIAGONAL, MAX_DIAGONAL)
    S = sys.U + np.diag(lam * Dc)
    rhs = -sys.g.copy()
    k = len(sys.V)
    Dv = np.clip(np.stack([sys.V[i, i] for i in range(k)]), MIN_DIAGONAL, MAX_DIAGONAL)
    Vd = sys.V.copy()
    for i in range(k):
        Vd[i, i] += lam * Dv[i]
    L = cholesky_soa(Vd)  # V_damped = L L^T per tuple
    B = forward_soa(L, sys.Jv)  # L^-1 Jv^T, (k, m, T)
    Br = np.einsum("krt,rt->kt", B, sys.r)
    # Eliminating the tuples: S -= W^T Vd^-1 W = sum Z^T Z, rhs += W^T Vd^-1 gv =
    # sum Z^T B r, with Z = B Jpose (k, 12, T) and W = Jv^T Jpose.
    _scatter_pairs(st, S, rhs, *_eliminated_pairs(st, B, sys.Jpose, Br))
    Vinv = Dp = None
    if st.refine_points:
        assert sys.Vp is not None and sys.obs_W is not None and sys.gp is not None
        Dp = _diag(sys.Vp)
        Vinv = np.linalg.inv(_damped(sys.Vp, Dp, lam))
        Y = sys.obs_W @ Vinv[st.obs_point]  # (O, 6, 3)
        fill = Y[st.pair_e1] @ sys.obs_W[st.pair_e2].transpose(0, 2, 1)
        fill = (st.pair_sum @ fill.reshape(-1, 36)).reshape(st.n, st.n, 6, 6)
        S -= fill.transpose(0, 2, 1, 3).reshape(S.shape)
        yg = np.einsum("oij,oj->oi", Y, sys.gp[st.obs_point])
        rhs += (st.obs_by_image @ yg).ravel()
    free = st.free
    dc = np.zeros_like(rhs)
    Sf = S[np.ix_(free, free)]
    try:
        dc[free] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(Sf), rhs[free])
    except np.linalg.LinAlgError:
        dc[free] = np.linalg.lstsq(Sf, rhs[free], rcond=None)[0]
    pose = dc.reshape(-1, POSE_SIZE)
    # Back-substitution: dv = -Vd^-1 Jv^T (r + Jpose dc) = -L^-T B (r + Jpose dc).
    dct = np.concatenate(
        [np.take(pose.T, st.vc_image1, axis=1), np.take(pose.T, st.vc_image2, axis=1)]
    )  # (12, T)
    Jd = np.einsum("crt,ct->rt", sys.Jpose, dct)
    dv = -backward_soa(L, Br + np.einsum("krt,rt->kt", B, Jd))
    # Decrease of the linear model: -g.d - d.H.d / 2 = (-g.d + lam d.D.d) / 2.
    pred = -float(sys.g @ dc) + lam * float((Dc * dc * dc)[free].sum())
    pred += -float((sys.gv * dv).sum()) + lam * float((Dv * dv * dv).sum())
    dp = None
    if st.refine_points:
        assert Vinv is not None and Dp is not None and sys.obs_W is not None
        assert sys.gp is not None
        wdc = np.einsum("oji,oj->oi", sys.obs_W, pose[st.obs_image])
        dp = -np.einsum("pij,pj->pi", Vinv, sys.gp + st.obs_by_point @ wdc)
        pred += -float((sys.gp * dp).sum()) + lam * float((Dp * dp * dp).sum())
    return dc, dv, dp, 0.5 * pred
