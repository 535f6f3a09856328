"""Mosaics of many overlapping scenes: block adjustment on a reference, one seamless output grid."""

from .output import load_models, scene_positions
from .report import write_report
from .run import mosaic
from .summary import MosaicSummary

__all__ = ["MosaicSummary", "load_models", "mosaic", "scene_positions", "write_report"]
