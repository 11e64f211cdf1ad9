"""`colmap-vc map`: pycolmap mapping of an (augmented) database, refined by the
people's keypoints, with a reason for every image it leaves out.

The pipeline (:mod:`.pipeline`) reads its inputs once (:mod:`.inputs`), runs the
strategy chosen in one place (:mod:`.choice`; the strategies, one function each, in
:mod:`.strategies`), refines, checks the cameras against the meshes
(:mod:`.priors`), scales to metres and writes the final model to ``OUTPUT/0``
(:mod:`.outputs`). Options and summary: :mod:`.options`.
"""

from .options import Mapper, MappingOptions, MappingSummary
from .outputs import OPTIONS_FILE, OUTPUT_MARKER, add_static_members_inplace
from .pipeline import run, run_incremental
from .priors import (
    apply_associations,
    leave_out_prior_outliers_inplace,
    leave_out_tilted_inplace,
    with_associated_ids,
)

__all__ = [
    "OPTIONS_FILE",
    "OUTPUT_MARKER",
    "Mapper",
    "MappingOptions",
    "MappingSummary",
    "add_static_members_inplace",
    "apply_associations",
    "leave_out_prior_outliers_inplace",
    "leave_out_tilted_inplace",
    "run",
    "run_incremental",
    "with_associated_ids",
]
