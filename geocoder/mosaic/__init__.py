"""Mosaics of many overlapping scenes: block adjustment on a reference, one seamless output grid."""

from .report import write_report
from .run import MosaicSummary, load_models, mosaic, scene_positions

__all__ = ["MosaicSummary", "load_models", "mosaic", "scene_positions", "write_report"]
