"""The synthetic world: deterministic scenes with people, ground truth, noisy priors."""

from .generate import SynthOptions, SynthSummary, generate, gt_reconstruction
from .gt import (
    AssociationScore,
    GtPersons,
    add_true_ids,
    association_score,
    gt_persons_path,
    read_gt_persons,
)
from .layout import Preset
from .noise import NOISE_LEVELS, NoiseLevel

__all__ = [
    "NOISE_LEVELS",
    "AssociationScore",
    "GtPersons",
    "NoiseLevel",
    "Preset",
    "SynthOptions",
    "SynthSummary",
    "add_true_ids",
    "association_score",
    "generate",
    "gt_persons_path",
    "gt_reconstruction",
    "read_gt_persons",
]
