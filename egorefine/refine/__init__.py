"""Predict (eq. 1 + splatting), correct (paper gate/gain or Kalman) and the refiner loop."""

from .correct import Correction, correct_disparity
from .predict import Prediction, predict_disparity
from .refiner import EgoMotionRefiner, RefinerOutput, RefinerState, SequenceResult, refine_sequence

__all__ = [
    "Correction",
    "correct_disparity",
    "Prediction",
    "predict_disparity",
    "EgoMotionRefiner",
    "RefinerOutput",
    "RefinerState",
    "SequenceResult",
    "refine_sequence",
]
