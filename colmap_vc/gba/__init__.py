"""Generalized bundle adjustment with virtual correspondences (paper Eq. 2-4).

For a VC tuple (pixel p1 in image i1, p2 in image i2), X1 is the first hit of ray 1
on the body and X2 that of ray 2; the rays meet iff X2 = X1 + a (X1 - o1) + b (o2 - o1).
GBA minimises the reprojection errors of X1 in i1 and X2 in i2 (plus classic points as
in BA), with the constraint exact (``Parametrization.HARD``) or penalised (``SOFT``), a
robust loss, and an optional prior from the human meshes that makes the result metric.
The math is in docs/gba.md.

Submodules: ``camera`` (projection and rotation derivatives), ``problem`` (options,
problem arrays, building from a reconstruction), ``model`` (parameters, residuals,
Jacobian), ``solver`` (LM with Schur complement, scipy), ``output`` (write-back, PLY).
"""

from .camera import SUPPORTED_MODELS
from .model import jacobian, pack, residuals
from .output import export_ply, refine_reconstruction
from .problem import (
    GbaOptions,
    GbaProblem,
    LossType,
    Parametrization,
    Solver,
    build_problem,
    vc_tuples_from_db,
)
from .solver import GbaResult, GbaSummary, solve

__all__ = [
    "SUPPORTED_MODELS",
    "GbaOptions",
    "GbaProblem",
    "GbaResult",
    "GbaSummary",
    "LossType",
    "Parametrization",
    "Solver",
    "build_problem",
    "export_ply",
    "jacobian",
    "pack",
    "refine_reconstruction",
    "residuals",
    "solve",
    "vc_tuples_from_db",
]
