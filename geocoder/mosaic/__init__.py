"""Mosaics of many overlapping scenes: block adjustment on a reference, one seamless output grid."""

from .run import MosaicSummary, load_models, mosaic

__all__ = ["MosaicSummary", "load_models", "mosaic"]
