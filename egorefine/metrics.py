"""Disparity and ego-motion metrics.

Every disparity metric takes an optional boolean ``mask`` ``(B, 1, H, W)`` (or any shape
matching the maps) of the pixels to score, typically "ground truth is known" combined with
"the method says this pixel is valid". Metrics return 0-dim tensors (differentiable where
that makes sense); :func:`evaluate_disparity` gathers them into a dict of Python floats.
Nothing is printed.
"""

from __future__ import annotations

import torch

from .core import ShapeError, check_float, check_shape

__all__ = [
    "epe",
    "bad_pixel_rate",
    "d1_error",
    "rmse",
    "density",
    "median_error",
    "evaluate_disparity",
    "distinct_levels",
    "temporal_consistency",
    "translation_error",
    "rotation_error_deg",
    "compose_motions",
    "motions_from_poses",
    "relative_pose_error",
    "absolute_trajectory_error",
    "evaluate_trajectory",
]


def _prepare(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    check_float(pred, "pred")
    check_float(gt, "gt")
    if pred.shape != gt.shape:
        raise ShapeError(f"gt: expected the shape of pred {tuple(pred.shape)}, got {tuple(gt.shape)}")
    if mask is None:
        mask = torch.isfinite(gt)
    elif mask.shape != pred.shape:
        raise ShapeError(f"mask: expected the shape of pred {tuple(pred.shape)}, got {tuple(mask.shape)}")
    mask = mask.bool() & torch.isfinite(gt) & torch.isfinite(pred)
    err = (pred - gt).abs()
    return torch.where(mask, err, torch.zeros_like(err)), mask


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    n = mask.sum()
    # An empty mask scores NaN: "no pixel to score" must not read as a perfect 0.
    return torch.where(n > 0, values.sum() / n.clamp_min(1), torch.full_like(values.sum(), float("nan")))


def epe(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """End-point error: mean ``|pred - gt|`` in pixels over ``mask``.

    >>> epe(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([1.5, 2.0, 3.0]))
    tensor(0.5000)
    """
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(err, mask)


def bad_pixel_rate(
    pred: torch.Tensor, gt: torch.Tensor, threshold: float, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Fraction (0..1) of scored pixels with ``|pred - gt| > threshold`` (bad-0.5, bad-1, bad-2 ...).

    >>> bad_pixel_rate(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([1.5, 2.0, 3.0]), 0.75)
    tensor(0.3333)
    """
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(((err > threshold) & mask).to(err.dtype), mask)


def d1_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """KITTI D1: fraction of pixels whose error exceeds both 3 px and 5 % of the true disparity."""
    err, mask = _prepare(pred, gt, mask)
    outlier = (err > 3.0) & (err > 0.05 * gt.abs()) & mask
    return _masked_mean(outlier.to(err.dtype), mask)


def rmse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Root-mean-square disparity error over ``mask``."""
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(err * err, mask).sqrt()


def median_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Median ``|pred - gt|`` over ``mask`` (NaN when nothing is scored)."""
    err, mask = _prepare(pred, gt, mask)
    sel = err[mask]
    return sel.median() if sel.numel() else torch.full((), float("nan"), dtype=err.dtype, device=err.device)


def density(valid: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Fraction of pixels in ``mask`` (default: all) that ``valid`` marks as having a disparity."""
    valid = valid.bool()
    mask = torch.ones_like(valid) if mask is None else mask.bool()
    return _masked_mean((valid & mask).float(), mask)


def evaluate_disparity(
    pred: torch.Tensor,
    gt: torch.Tensor,
    valid: torch.Tensor | None = None,
    gt_mask: torch.Tensor | None = None,
    thresholds: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0),
) -> dict[str, float]:
    """All disparity metrics at once, as Python floats.

    Errors are scored on ``valid & gt_mask`` (the pixels the method claims, where truth
    exists); ``density`` is the fraction of ``gt_mask`` pixels the method marks valid.

    Returns:
        ``{"epe", "median", "rmse", "d1", "bad-0.5", "bad-1", ..., "density"}``.
    """
    gt_mask = torch.isfinite(gt) & (gt > 0) if gt_mask is None else gt_mask.bool()
    valid = torch.ones_like(gt_mask) if valid is None else valid.bool()
    scored = valid & gt_mask
    out = {
        "epe": epe(pred, gt, scored),
        "median": median_error(pred, gt, scored),
        "rmse": rmse(pred, gt, scored),
        "d1": d1_error(pred, gt, scored),
    }
    for t in thresholds:
        out[f"bad-{t:g}"] = bad_pixel_rate(pred, gt, t, scored)
    out["density"] = density(valid, gt_mask)
    return {k: float(v) for k, v in out.items()}


def distinct_levels(values: torch.Tensor, resolution: float = 1e-3) -> int:
    """Number of distinct values (to ``resolution``) in ``values``: the depth layers along a row.

    >>> distinct_levels(torch.tensor([3.0, 3.0, 4.0, 4.0, 3.5]))
    3
    """
    return int(torch.unique(torch.round(values.flatten() / resolution)).numel())


def temporal_consistency(
    disparity: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean absolute frame-to-frame change of the error, ``|e_t - e_{t-1}|`` with ``e = pred - gt``.

    A method whose error flickers from frame to frame scores high even at a low EPE. It is
    computed on the error, not the disparity, so that true scene motion is not penalised.

    Args:
        disparity: ``(T, ...)`` a sequence of disparity maps.
        gt: ``(T, ...)`` ground truth.
        mask: ``(T, ...)`` pixels to score (both frames of a pair must be in it).
    """
    if disparity.shape != gt.shape or disparity.shape[0] < 2:
        raise ShapeError(f"disparity: expected (T>=2, ...) matching gt {tuple(gt.shape)}, got {tuple(disparity.shape)}")
    err = disparity - gt
    mask = torch.isfinite(err) if mask is None else mask.bool() & torch.isfinite(err)
    pair = mask[1:] & mask[:-1]
    diff = (err[1:] - err[:-1]).abs()
    return _masked_mean(torch.where(pair, diff, torch.zeros_like(diff)), pair)


def translation_error(est: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Norm of the translation difference of rigid motions ``(B, 4, 4)``, per item ``(B,)``, in metres."""
    check_shape(est, ["B", "4", "4"], "est")
    check_shape(gt, ["B", "4", "4"], "gt", {"B": est.shape[0]})
    return (est[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1)


def rotation_error_deg(est: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Angle of ``R_est^T R_gt`` in degrees, per item ``(B,)``."""
    check_shape(est, ["B", "4", "4"], "est")
    check_shape(gt, ["B", "4", "4"], "gt", {"B": est.shape[0]})
    rel = est[:, :3, :3].transpose(1, 2) @ gt[:, :3, :3]
    cos = (rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
    vee = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], dim=-1)
    # atan2(sin, cos) rather than acos(cos): acos loses angles below ~0.02 degrees in float32.
    return torch.rad2deg(torch.atan2(0.5 * vee.norm(dim=-1), cos))


def compose_motions(motions: torch.Tensor) -> torch.Tensor:
    """Poses ``camera_0_T_camera_t`` ``(T, 4, 4)`` from per-frame motions ``camera_t_T_camera_{t-1}`` ``(T, 4, 4)``.

    ``motions[0]`` is ignored (the first frame is the origin), as the refiner returns the identity there.

    >>> step = torch.eye(4).repeat(3, 1, 1); step[:, 2, 3] = -0.1  # static points come 0.1 m closer
    >>> compose_motions(step)[:, 2, 3]  # so the camera moved 0.1 m forward each frame
    tensor([0.0000, 0.1000, 0.2000])
    """
    check_shape(motions, ["T", "4", "4"], "motions")
    poses = [torch.eye(4, dtype=motions.dtype, device=motions.device)]
    for motion in motions[1:]:  # a loop over time: each pose needs the previous one
        poses.append(poses[-1] @ torch.linalg.inv(motion))
    return torch.stack(poses)


def motions_from_poses(poses: torch.Tensor) -> torch.Tensor:
    """Per-frame motions ``camera_t_T_camera_{t-1}`` ``(T, 4, 4)`` from poses ``world_T_camera_t`` ``(T, 4, 4)``.

    The inverse of :func:`compose_motions` (up to the first pose, which it cannot recover): ``motions[0]`` is the
    identity, ``motions[t] = inv(poses[t]) @ poses[t - 1]``.

    >>> step = torch.eye(4).repeat(3, 1, 1); step[:, 2, 3] = -0.1
    >>> torch.allclose(motions_from_poses(compose_motions(step))[1:], step[1:])
    True
    """
    check_shape(poses, ["T", "4", "4"], "poses")
    first = torch.eye(4, dtype=poses.dtype, device=poses.device)[None]
    return torch.cat([first, torch.linalg.solve(poses[1:], poses[:-1])])


def relative_pose_error(est: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    """RPE over consecutive frames of per-frame motions ``(T, 4, 4)`` (``t = 0`` skipped).

    Returns:
        ``{"translation_rmse_m", "translation_median_m", "rotation_mean_deg", "rotation_median_deg"}``.
    """
    check_shape(est, ["T", "4", "4"], "est")
    check_shape(gt, ["T", "4", "4"], "gt", {"T": est.shape[0]})
    t_err = translation_error(est[1:], gt[1:])
    r_err = rotation_error_deg(est[1:], gt[1:])
    return {
        "translation_rmse_m": float(t_err.pow(2).mean().sqrt()),
        "translation_median_m": float(t_err.median()),
        "rotation_mean_deg": float(r_err.mean()),
        "rotation_median_deg": float(r_err.median()),
    }


def absolute_trajectory_error(est_poses: torch.Tensor, gt_poses: torch.Tensor, align: bool = True) -> float:
    """ATE: RMSE (metres) of camera positions ``(T, 4, 4)`` after a rigid alignment of ``est`` onto ``gt``.

    The alignment is the least-squares rotation and translation (Kabsch/Umeyama without scale: a stereo
    rig measures metric scale, so scale is not fitted away). ``align=False`` compares the raw positions.
    """
    check_shape(est_poses, ["T", "4", "4"], "est_poses")
    check_shape(gt_poses, ["T", "4", "4"], "gt_poses", {"T": est_poses.shape[0]})
    p, q = est_poses[:, :3, 3].double(), gt_poses[:, :3, 3].double()
    if align:
        mp, mq = p.mean(0), q.mean(0)
        U, _, Vh = torch.linalg.svd((q - mq).T @ (p - mp))
        # Reflection guard: force det(R) = +1.
        D = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.linalg.det(U @ Vh)))], dtype=p.dtype))
        R = U @ D @ Vh
        p = (p - mp) @ R.T + mq
    return float((p - q).pow(2).sum(-1).mean().sqrt())


def evaluate_trajectory(est_poses: torch.Tensor, gt_poses: torch.Tensor) -> dict[str, float]:
    """Trajectory metrics of ``world_T_camera`` poses ``(T, 4, 4)`` against truth, as Python floats.

    Frame-to-frame RPE (:func:`relative_pose_error` of :func:`motions_from_poses`) and the ATE after a rigid
    alignment (:func:`absolute_trajectory_error`); both trajectories must have the same frames, in order.

    Args:
        est_poses: ``(T, 4, 4)`` estimated poses, ``T >= 2``.
        gt_poses: ``(T, 4, 4)`` true poses of the same frames.

    Returns:
        ``{"frames", "rpe_translation_rmse_m", "rpe_translation_median_m", "rpe_rotation_mean_deg",
        "rpe_rotation_median_deg", "ate_rmse_m", "path_length_m"}`` (``path_length_m``: the true path's length).

    Example:
        >>> gt = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1); gt[:, 2, 3] = torch.tensor([0.0, 1.0, 2.0])
        >>> est = gt.clone(); est[2, 2, 3] = 2.5
        >>> m = evaluate_trajectory(est, gt)
        >>> m["frames"], round(m["rpe_translation_rmse_m"] ** 2, 6), m["path_length_m"]  # steps off by 0 and 0.5 m
        (3.0, 0.125, 2.0)
    """
    check_shape(est_poses, ["T", "4", "4"], "est_poses")
    check_shape(gt_poses, ["T", "4", "4"], "gt_poses", {"T": est_poses.shape[0]})
    if est_poses.shape[0] < 2:
        raise ShapeError(f"est_poses: expected at least 2 poses, got {est_poses.shape[0]}")
    est, gt = est_poses.double(), gt_poses.double()
    rpe = relative_pose_error(motions_from_poses(est), motions_from_poses(gt))
    out = {"frames": float(est.shape[0])}
    out.update({f"rpe_{k}": v for k, v in rpe.items()})
    out["ate_rmse_m"] = absolute_trajectory_error(est, gt)
    out["path_length_m"] = float((gt[1:, :3, 3] - gt[:-1, :3, 3]).norm(dim=-1).sum())
    return out
