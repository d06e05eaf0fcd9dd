"""Dense stereo matching: cost volumes (SAD, ZNCC, census), box or SGM aggregation,
winner-takes-all with sub-pixel fit or soft-argmin, left-right / uniqueness / texture checks and
speckle removal."""

from ._sgm_numba import release_workspace as release_sgm_workspace
from .cost import COSTS, INVALID_COST, census_transform, cost_volume, prefilter_xsobel
from .matching import INVALID_VARIANCE, BlockMatching, StereoOutput, block_matching, fill_invalid, match_stereo
from .opencv import match_opencv, stereo_bm, stereo_sgbm
from .regions import mask_boxes, match_stereo_regions
from .residual import match_residual
from .scale import match_half_resolution
from .sgm import sgm_aggregate
from .speckle import remove_speckles

__all__ = [
    "block_matching",
    "match_stereo",
    "fill_invalid",
    "match_residual",
    "match_half_resolution",
    "match_stereo_regions",
    "match_opencv",
    "stereo_bm",
    "stereo_sgbm",
    "mask_boxes",
    "BlockMatching",
    "StereoOutput",
    "cost_volume",
    "sgm_aggregate",
    "remove_speckles",
    "release_sgm_workspace",
    "prefilter_xsobel",
    "census_transform",
    "COSTS",
    "INVALID_COST",
    "INVALID_VARIANCE",
]
