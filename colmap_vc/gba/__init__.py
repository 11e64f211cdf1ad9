"""Generalized bundle adjustment: the people's tracks in COLMAP's own Ceres problem.

``ceres``: COLMAP's bundle adjustment with extra, individually weighted observations
(:func:`colmap_vc.gba.ceres.bundle_adjust_inplace`); ``correlated``: the noise of
the surface samples, a spread and a correlation by pixel distance, estimated from
the data; ``noise``: residuals and a shared-offset noise per (image, person), what
a keypoint is worth against the cameras' up; ``up``: those up residuals. The
refinement that uses them is :mod:`colmap_vc.keypoint_ba`; docs/gba.md has the
residuals, the noise model and what each kind of evidence measured.
"""
