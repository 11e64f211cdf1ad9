"""The synthetic world: deterministic scenes with people, ground truth, noisy priors."""

from .generate import SynthOptions, SynthSummary, generate, gt_reconstruction
from .layout import Preset
from .noise import NOISE_LEVELS, NoiseLevel

__all__ = [
    "NOISE_LEVELS",
    "NoiseLevel",
    "Preset",
    "SynthOptions",
    "SynthSummary",
    "generate",
    "gt_reconstruction",
]
