"""Least-squares block adjustment (pure numpy / scipy.sparse)."""
