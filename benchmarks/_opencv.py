"""OpenCV's stereo matchers as their users run them, for the benchmarks and tests: one definition, in the package
(:mod:`egorefine.stereo.opencv`, which the demo uses too)."""

from __future__ import annotations

from egorefine.stereo.opencv import BM_BLOCK, SGBM_BLOCK, compute, stereo_bm, stereo_sgbm

__all__ = ["BM_BLOCK", "SGBM_BLOCK", "stereo_bm", "stereo_sgbm", "compute"]
