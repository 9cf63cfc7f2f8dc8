"""Pseudo-labels and VLM image embeddings: 2-D masks and dense features lifted to 3-D with the LiDAR.

numpy + opencv only (no torch). Modules: backends (Segmenter / ImageEmbedder interfaces, file
backends), simulated (SIMULATED backends for synthetic data), lift (projection and lookup),
aggregate (multi-frame), raycast (free space), voting (labels, feature means), generate (driver,
output format and readers). File layout for real VLM outputs: docs/vlm_files.md.
"""

from .backends import FileImageEmbedder, FileSegmenter, ImageEmbedder, Segmenter
from .generate import (PseudoLabelConfig, PseudoLabelDir, PseudoSample, build_sample, generate,
                       load_pseudo_labels, load_voxel_embeds, pseudo_sample)
from .simulated import (SimEmbedderConfig, SimSegmenterConfig, SimulatedImageEmbedder, SimulatedSegmenter,
                        similarity_stats)

__all__ = [
    "FileImageEmbedder", "FileSegmenter", "ImageEmbedder", "Segmenter", "PseudoLabelConfig", "PseudoLabelDir",
    "PseudoSample", "build_sample", "generate", "load_pseudo_labels", "load_voxel_embeds", "pseudo_sample",
    "SimEmbedderConfig", "SimSegmenterConfig", "SimulatedImageEmbedder", "SimulatedSegmenter", "similarity_stats",
]
