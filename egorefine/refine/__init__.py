"""Predict (eq. 1 + splatting), correct (paper gate/gain or Kalman) and the refiner loop."""

from .correct import CorrectDisparity, Correction, correct_disparity
from .cracks import close_cracks
from .health import Status
from .learning import NET_INPUTS, ConfidenceNet, CorrectionNet, measurement_features
from .options import (
    CorrectionOptions,
    PredictionOptions,
    ScheduleOptions,
    SearchOptions,
    StereoOptions,
    TrackingOptions,
)
from .predict import PredictDisparity, Prediction, fill_holes_background, predict_disparity
from .refiner import EgoMotionRefiner, RefinerOutput, RefinerState
from .sequence import SequenceResult, refine_sequence

__all__ = [
    "Status",
    "ConfidenceNet",
    "CorrectionNet",
    "NET_INPUTS",
    "measurement_features",
    "CorrectDisparity",
    "Correction",
    "correct_disparity",
    "close_cracks",
    "PredictDisparity",
    "Prediction",
    "fill_holes_background",
    "predict_disparity",
    "EgoMotionRefiner",
    "StereoOptions",
    "TrackingOptions",
    "PredictionOptions",
    "CorrectionOptions",
    "SearchOptions",
    "ScheduleOptions",
    "RefinerOutput",
    "RefinerState",
    "SequenceResult",
    "refine_sequence",
]
