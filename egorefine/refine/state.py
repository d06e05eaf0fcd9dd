"""What the refiner hands from one frame to the next, and what it answers per frame.

:class:`RefinerState` is explicit (``out, state = refiner(left, right, K, baseline, state)``): nothing is kept on
the module between calls, so one refiner serves many sequences and a state can be saved, inspected or detached.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["RefinerState", "RefinerOutput"]


class RefinerState(NamedTuple):
    """What one frame hands to the next. All tensors are batched; ``frame`` counts calls.

    Attributes:
        image: ``(B, 1, H, W)`` previous left image, grey.
        keypoints: ``(B, N, 2)`` feature positions in ``image``.
        weights: ``(B, N)`` live-track weights (0 = empty slot).
        disparity: ``(B, 1, H, W)`` previous refined disparity.
        variance: ``(B, 1, H, W)`` its per-pixel variance, px^2.
        valid: ``(B, 1, H, W)`` where ``disparity`` holds a real (not hole-filled) value.
        outlier_count: ``(B, 1, H, W)`` consecutive gated-out verifications per pixel (Kalman reset).
        motion: ``(B, 4, 4)`` last estimated ``camera_t_T_camera_{t-1}`` (centres the next search).
        key_disparity, key_variance, key_valid: ``(B, 1, H, W)`` the map of the last verification frame
            (the keyframe); every prediction starts from it, not from the previous prediction.
        key_motion: ``(B, 4, 4)`` ``camera_t_T_camera_key``, the motions composed since the keyframe.
        frame: index of the frame this state was produced on.
        since_stereo: frames since stereo last ran (0 = it ran on ``frame``).
        pyramid: the tracker's image pyramid of ``image`` (levels of ``(B, 1, H_l, W_l)``), built once per frame
            and reused when tracking into the next one; None: built from ``image`` when needed.
        matched: ``(B,)`` int64, the pixels the verification matcher itself (before any ``fill``) matched at the
            last accepted verification: what the next one's match count is compared with to tell a failed stereo
            pair (None: the prediction's valid count is used).

    Example:
        >>> from egorefine.data import render_sequence
        >>> from egorefine.refine import EgoMotionRefiner, TrackingOptions
        >>> seq = render_sequence(num_frames=2, height=40, width=56)
        >>> refiner = EgoMotionRefiner(max_disparity=8, tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> K, b = seq.K[None], torch.tensor([seq.baseline])
        >>> _, state = refiner(seq.left[:1], seq.right[:1], K, b)  # no state: a new sequence
        >>> state.frame, state.disparity.shape, state.keypoints.shape, state.weights.shape
        (0, torch.Size([1, 1, 40, 56]), torch.Size([1, 64, 2]), torch.Size([1, 64]))
        >>> _, state = refiner(seq.left[1:], seq.right[1:], K, b, state)
        >>> state.frame, state.since_stereo  # verify_every=5: no stereo on frame 1
        (1, 1)
    """

    image: torch.Tensor
    keypoints: torch.Tensor
    weights: torch.Tensor
    disparity: torch.Tensor
    variance: torch.Tensor
    valid: torch.Tensor
    outlier_count: torch.Tensor
    motion: torch.Tensor
    key_disparity: torch.Tensor
    key_variance: torch.Tensor
    key_valid: torch.Tensor
    key_motion: torch.Tensor
    frame: int
    since_stereo: int
    pyramid: tuple[torch.Tensor, ...] | None = None
    matched: torch.Tensor | None = None

    def detach(self) -> RefinerState:
        """The same state with every tensor detached from the autograd graph: truncated backpropagation
        through time. The next frame's outputs then depend on this state's values but gradients stop here.

        Example:
            >>> import torch
            >>> x = torch.ones(1, 1, 2, 2, requires_grad=True)
            >>> eye = torch.eye(4)[None]
            >>> s = RefinerState(x, x[:, 0, :1], x[:, 0, 0], x * 2, x, x > 0, x, eye, x, x, x > 0, eye, 0, 0, (x,))
            >>> d = s.detach()
            >>> d.disparity.requires_grad, d.pyramid[0].requires_grad, s.disparity.requires_grad
            (False, False, True)
        """
        def cut(value):
            if isinstance(value, torch.Tensor):
                return value.detach()
            if isinstance(value, tuple):
                return tuple(cut(v) for v in value)
            return value

        return RefinerState(*(cut(v) for v in self))


class RefinerOutput(NamedTuple):
    """The refiner's answer for one frame.

    Attributes:
        disparity: ``(B, 1, H, W)`` refined disparity, px; hole-filled pixels hold a value too.
        valid: ``(B, 1, H, W)`` bool, pixels with a real (measured or predicted) disparity.
        motion: ``(B, 4, 4)`` ``camera_t_T_camera_{t-1}``; identity on the first frame and where
            the motion could not be estimated (see ``motion_ok``).
        stereo_ran: whether stereo matching ran on this frame.
        variance: ``(B, 1, H, W)`` per-pixel variance, px^2.
        confidence: ``(B, 1, H, W)`` in [0, 1]; low on hole-filled pixels.
        motion_ok: ``(B,)`` bool, the ego-motion solve succeeded (True on the first frame).
        num_tracks: ``(B,)`` features that were tracked into this frame.
        status: ``(B,)`` int64 bits of :class:`~egorefine.refine.health.Status`: what happened to each item on
            this frame (stereo forced, motion failed, scene change, measurement rejected, prediction reset, exposure
            jump); 0 on an ordinary frame.

    Example:
        >>> from egorefine.data import render_sequence
        >>> from egorefine.refine import EgoMotionRefiner, TrackingOptions
        >>> seq = render_sequence(num_frames=1, height=40, width=56)
        >>> refiner = EgoMotionRefiner(max_disparity=8, tracking=TrackingOptions(max_features=64, min_tracks=16))
        >>> out, _ = refiner(seq.left, seq.right, seq.K[None], torch.tensor([seq.baseline]))
        >>> out.disparity.shape, out.valid.dtype, out.motion.shape, out.stereo_ran  # stereo runs on frame 0
        (torch.Size([1, 1, 40, 56]), torch.bool, torch.Size([1, 4, 4]), True)
        >>> out.motion_ok.tolist(), out.status.tolist()
        ([True], [0])
    """

    disparity: torch.Tensor
    valid: torch.Tensor
    motion: torch.Tensor
    stereo_ran: bool
    variance: torch.Tensor
    confidence: torch.Tensor
    motion_ok: torch.Tensor
    num_tracks: torch.Tensor
    status: torch.Tensor
