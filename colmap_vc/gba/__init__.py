"""Generalized bundle adjustment: the people's tracks in COLMAP's own Ceres problem.

``ceres``: COLMAP's bundle adjustment with extra, individually weighted observations
(:func:`colmap_vc.gba.ceres.bundle_adjust_inplace`); ``noise``: the noise of each
person's observations in each image, estimated from the data. The refinement that
uses them is :mod:`colmap_vc.keypoint_ba`; docs/gba.md has the residuals, the noise
model and what each kind of evidence measured.
"""
