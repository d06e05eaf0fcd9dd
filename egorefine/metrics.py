"""Disparity and ego-motion metrics.

Every disparity metric takes an optional boolean ``mask`` ``(B, 1, H, W)`` (or any shape
matching the maps) of the pixels to score, typically "ground truth is known" combined with
"the method says this pixel is valid". Metrics return 0-dim tensors (differentiable where
that makes sense); :func:`evaluate_disparity` gathers them into a dict of Python floats.
Nothing is printed.
"""

from __future__ import annotations

import torch

from .core import ShapeError, ValueRangeError, check_float, check_shape

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
    "tile_shift",
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
    """End-point error: the mean absolute disparity error ``|pred - gt|`` in pixels over the scored pixels.

    The standard stereo accuracy figure (Middlebury, KITTI). Pixels where ``gt`` or ``pred`` is not finite are never
    scored; an empty selection gives NaN, so "no pixel to score" cannot read as a perfect 0.

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels, float.
        gt: true disparity, the shape of ``pred``.
        mask: bool, the shape of ``pred``: the pixels to score; default every pixel with a finite ``gt``.

    Returns:
        0-dim tensor, differentiable with respect to ``pred``.

    Example:
        >>> epe(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([1.5, 2.0, 3.0]))
        tensor(0.5000)
    """
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(err, mask)


def bad_pixel_rate(
    pred: torch.Tensor, gt: torch.Tensor, threshold: float, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Share of the scored pixels whose error ``|pred - gt|`` exceeds ``threshold`` px (bad-0.5, bad-1, bad-2 ...).

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels.
        gt: true disparity, the shape of ``pred``.
        threshold: error in pixels above which a pixel counts as bad; sub-pixel methods are judged at 0.5 or 1,
            pixel-accurate ones at 2 or 3.
        mask: bool, the shape of ``pred``: the pixels to score; default every pixel with a finite ``gt``.

    Returns:
        0-dim tensor in [0, 1] (NaN when nothing is scored).

    Example:
        >>> bad_pixel_rate(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([1.5, 2.0, 3.0]), 0.75)
        tensor(0.3333)
    """
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(((err > threshold) & mask).to(err.dtype), mask)


def d1_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """KITTI's D1 outlier rate: the share of scored pixels whose error exceeds both 3 px and 5 % of the true disparity.

    The relative term forgives large errors on near surfaces (large disparities), as the KITTI 2015 benchmark does.

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels.
        gt: true disparity, the shape of ``pred``.
        mask: bool, the shape of ``pred``: the pixels to score; default every pixel with a finite ``gt``.

    Returns:
        0-dim tensor in [0, 1] (NaN when nothing is scored).

    Example:
        >>> d1_error(torch.tensor([10.0, 100.0]), torch.tensor([14.0, 96.0]))  # 4 px is over 5 % of 14, not of 96
        tensor(0.5000)
    """
    err, mask = _prepare(pred, gt, mask)
    outlier = (err > 3.0) & (err > 0.05 * gt.abs()) & mask
    return _masked_mean(outlier.to(err.dtype), mask)


def rmse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Root-mean-square disparity error in pixels over the scored pixels (weighs large errors more than :func:`epe`).

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels.
        gt: true disparity, the shape of ``pred``.
        mask: bool, the shape of ``pred``: the pixels to score; default every pixel with a finite ``gt``.

    Returns:
        0-dim tensor (NaN when nothing is scored).

    Example:
        >>> rmse(torch.tensor([1.0, 3.0]), torch.tensor([1.0, 1.0]))
        tensor(1.4142)
    """
    err, mask = _prepare(pred, gt, mask)
    return _masked_mean(err * err, mask).sqrt()


def median_error(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Median absolute disparity error ``|pred - gt|`` in pixels over the scored pixels: robust to a few gross errors.

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels.
        gt: true disparity, the shape of ``pred``.
        mask: bool, the shape of ``pred``: the pixels to score; default every pixel with a finite ``gt``.

    Returns:
        0-dim tensor (NaN when nothing is scored).

    Example:
        >>> median_error(torch.tensor([1.0, 2.0, 9.0]), torch.tensor([1.5, 2.0, 3.0]))
        tensor(0.5000)
    """
    err, mask = _prepare(pred, gt, mask)
    sel = err[mask]
    return sel.median() if sel.numel() else torch.full((), float("nan"), dtype=err.dtype, device=err.device)


def density(valid: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Share of the pixels in ``mask`` that ``valid`` marks as having a disparity.

    Args:
        valid: ``(B, 1, H, W)`` (or any shape) bool (or 0/1): where the method gives a value.
        mask: bool, the shape of ``valid``: the pixels that count, e.g. those with ground truth; default all.

    Returns:
        0-dim float tensor in [0, 1] (NaN when ``mask`` is empty).

    Example:
        >>> density(torch.tensor([True, False, True, True]))
        tensor(0.7500)
    """
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
    """All disparity metrics of one prediction at once, as Python floats.

    Errors are scored on ``valid & gt_mask`` (the pixels the method claims, where truth exists); ``density`` is the
    share of the ``gt_mask`` pixels that the method marks valid, so a method cannot improve its errors unseen by
    dropping hard pixels.

    Args:
        pred: ``(B, 1, H, W)`` (or any shape) predicted disparity in pixels.
        gt: true disparity, the shape of ``pred``.
        valid: bool, the shape of ``pred``: the method's own valid mask; default all pixels.
        gt_mask: bool, the shape of ``pred``: where truth exists; default where ``gt`` is finite and > 0 (KITTI's
            and the renderer's convention for "no truth").
        thresholds: the bad-x thresholds in pixels; default 0.5, 1, 2 and 3 px, from sub-pixel to KITTI's accuracy.

    Returns:
        ``{"epe", "median", "rmse", "d1", "bad-0.5", "bad-1", "bad-2", "bad-3", "density"}`` (one ``bad-x`` key per
        threshold, named with ``{x:g}``).

    Example:
        >>> m = evaluate_disparity(torch.tensor([[1.0, 2.0], [4.0, 9.0]]), torch.tensor([[1.5, 2.0], [3.0, 0.0]]))
        >>> sorted(m), m["epe"], m["density"]  # the pixel without truth (gt 0) is not scored
        (['bad-0.5', 'bad-1', 'bad-2', 'bad-3', 'd1', 'density', 'epe', 'median', 'rmse'], 0.5, 1.0)
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
    """Number of distinct values, to ``resolution``, in ``values``: the depth layers along a row of a disparity map.

    A pixel-accurate matcher gives few levels on a slanted surface, a sub-pixel one many: a plain count of what the
    paper's figures show as staircases.

    Args:
        values: any shape; flattened.
        resolution: values closer than this (after rounding to multiples of it) count as one level; default
            1e-3 px, far below any sub-pixel step a matcher resolves.

    Returns:
        Python int.

    Example:
        >>> distinct_levels(torch.tensor([3.0, 3.0, 4.0, 4.0, 3.5]))
        3
    """
    return int(torch.unique(torch.round(values.flatten() / resolution)).numel())


def temporal_consistency(
    disparity: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean absolute frame-to-frame change of the error, ``|e_t - e_{t-1}|`` with ``e = pred - gt``.

    A method whose error flickers from frame to frame scores high even at a low EPE. It is computed on the error, not
    the disparity, so that true scene motion is not penalised.

    Args:
        disparity: ``(T, ...)`` a sequence of disparity maps, ``T >= 2``, e.g. ``(T, B, 1, H, W)``.
        gt: ``(T, ...)`` ground truth, the shape of ``disparity``.
        mask: ``(T, ...)`` bool, pixels to score (both frames of a pair must be in it); default where the error is
            finite.

    Returns:
        0-dim tensor in pixels (NaN when no pair is scored).

    Raises:
        ShapeError: shapes differ or ``T < 2``.

    Example:
        >>> gt = torch.ones(3, 1, 2, 2)
        >>> temporal_consistency(gt + torch.tensor([0.0, 0.5, 0.5]).view(3, 1, 1, 1), gt)  # one jump of 0.5 px
        tensor(0.2500)
    """
    if disparity.shape != gt.shape or disparity.shape[0] < 2:
        raise ShapeError(f"disparity: expected (T>=2, ...) matching gt {tuple(gt.shape)}, got {tuple(disparity.shape)}")
    err = disparity - gt
    mask = torch.isfinite(err) if mask is None else mask.bool() & torch.isfinite(err)
    pair = mask[1:] & mask[:-1]
    diff = (err[1:] - err[:-1]).abs()
    return _masked_mean(torch.where(pair, diff, torch.zeros_like(diff)), pair)


def tile_shift(
    disparity: torch.Tensor,
    reference: torch.Tensor,
    mask: torch.Tensor | None = None,
    tile: int = 32,
    min_share: float = 0.5,
) -> torch.Tensor:
    """Median over image tiles of ``|median(disparity - reference)|`` in each tile: a map's systematic shift.

    Drift is a systematic change: a map that slides, as a whole or region by region, away from where it was. A
    per-pixel distance between two maps cannot separate it from their noise: two independent measurements of the
    same surface differ per pixel by about their noise however long the sequence, and a filter that averages
    measurements moves away from a noisy first map while it converges. A tile's median difference keeps a shift
    shared by the tile and averages independent per-pixel noise away, so a still camera's refined map compared with
    its (motion-compensated) first map scores the drift, not the first map's noise. The median over tiles keeps a
    few tiles with a real change (an occluder) from dominating.

    Args:
        disparity: ``(B, 1, H, W)`` maps (any shape ending in ``(H, W)``).
        reference: the maps to compare with, the shape of ``disparity``.
        mask: bool, the shape of ``disparity``, pixels to compare; default where both are finite.
        tile: tile side in pixels (default 32: several matching windows, so a tile's median averages many
            independent errors while a region's shift still fills it). Partial tiles at the right and bottom edges
            are left out.
        min_share: a tile counts when at least this share of its pixels is in the mask (default 0.5).

    Returns:
        0-dim tensor in pixels over the counted tiles of every item (NaN when none counts).

    Raises:
        ShapeError: shapes differ, or the maps are smaller than one tile.
        ValueRangeError: ``tile < 1`` or ``min_share`` outside (0, 1].

    Example:
        >>> ref = torch.rand(1, 1, 64, 64) * 10
        >>> noisy = ref + 0.2 * torch.randn(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
        >>> bool(tile_shift(noisy, ref) < 0.05)  # per-pixel noise of 0.2 px is averaged away
        True
        >>> tile_shift(ref + 0.1, ref)  # a shift of the whole map is kept
        tensor(0.1000)
    """
    check_float(disparity, "disparity")
    if disparity.shape != reference.shape or disparity.dim() < 2:
        raise ShapeError(f"reference: expected the shape of disparity {tuple(disparity.shape)}, "
                         f"got {tuple(reference.shape)}")
    if mask is not None and mask.shape != disparity.shape:
        raise ShapeError(f"mask: expected the shape of disparity {tuple(disparity.shape)}, got {tuple(mask.shape)}")
    if int(tile) < 1:
        raise ValueRangeError(f"tile: expected >= 1, got {tile}")
    if not 0.0 < float(min_share) <= 1.0:
        raise ValueRangeError(f"min_share: expected in (0, 1], got {min_share}")
    H, W = disparity.shape[-2:]
    ny, nx = H // tile, W // tile
    if ny == 0 or nx == 0:
        raise ShapeError(f"disparity: expected at least one {tile}x{tile} tile, got {H}x{W}")
    diff = disparity - reference.to(disparity.dtype)
    ok = torch.isfinite(diff) if mask is None else mask.bool() & torch.isfinite(diff)
    diff = torch.where(ok, diff, torch.full_like(diff, float("nan")))

    def tiles(x: torch.Tensor) -> torch.Tensor:  # (..., H, W) -> (N, tile * tile)
        x = x[..., : ny * tile, : nx * tile].reshape(-1, ny, tile, nx, tile)
        return x.permute(0, 1, 3, 2, 4).reshape(-1, tile * tile)

    share = tiles(ok).float().mean(-1)
    medians = tiles(diff).nanmedian(-1).values
    counted = share >= min_share
    if not bool(counted.any()):
        return diff.new_tensor(float("nan"))
    return medians[counted].abs().median()


def translation_error(est: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Norm of the difference of the translations of rigid motions, per item, in metres.

    Args:
        est: ``(B, 4, 4)`` estimated motions (or poses).
        gt: ``(B, 4, 4)`` true ones.

    Returns:
        ``(B,)`` metres.

    Example:
        >>> gt = torch.eye(4)[None]; est = gt.clone(); est[0, :3, 3] = torch.tensor([0.3, 0.0, 0.4])
        >>> translation_error(est, gt)
        tensor([0.5000])
    """
    check_shape(est, ["B", "4", "4"], "est")
    check_shape(gt, ["B", "4", "4"], "gt", {"B": est.shape[0]})
    return (est[:, :3, 3] - gt[:, :3, 3]).norm(dim=-1)


def rotation_error_deg(est: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Angle of the rotation ``R_est^T R_gt`` between estimated and true motions, per item, in degrees.

    Args:
        est: ``(B, 4, 4)`` estimated motions (or poses); only the rotation blocks are read.
        gt: ``(B, 4, 4)`` true ones.

    Returns:
        ``(B,)`` degrees in [0, 180].

    Example:
        >>> from egorefine.geometry import se3_exp
        >>> turn = se3_exp(torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.1, 0.0]], dtype=torch.float64))  # 0.1 rad about y
        >>> rotation_error_deg(turn, torch.eye(4, dtype=torch.float64)[None]).round(decimals=4)
        tensor([5.7296], dtype=torch.float64)
    """
    check_shape(est, ["B", "4", "4"], "est")
    check_shape(gt, ["B", "4", "4"], "gt", {"B": est.shape[0]})
    rel = est[:, :3, :3].transpose(1, 2) @ gt[:, :3, :3]
    cos = (rel.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
    vee = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], dim=-1)
    # atan2(sin, cos) rather than acos(cos): acos loses angles below ~0.02 degrees in float32.
    return torch.rad2deg(torch.atan2(0.5 * vee.norm(dim=-1), cos))


def compose_motions(motions: torch.Tensor) -> torch.Tensor:
    """Poses ``camera_0_T_camera_t`` from per-frame motions ``camera_t_T_camera_{t-1}``, chained from the first frame.

    ``motions[0]`` is ignored (the first frame is the origin), as the refiner returns the identity there.

    Args:
        motions: ``(T, 4, 4)`` per-frame rigid motions, e.g. one batch item of the ``motion`` of
            :func:`egorefine.refine.refine_sequence`.

    Returns:
        ``(T, 4, 4)`` poses; ``poses[0]`` is the identity.

    Example:
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
    """Per-frame motions ``camera_t_T_camera_{t-1}`` from poses ``world_T_camera_t``.

    The inverse of :func:`compose_motions` (up to the first pose, which it cannot recover): ``motions[0]`` is the
    identity, ``motions[t] = inv(poses[t]) @ poses[t - 1]``.

    Args:
        poses: ``(T, 4, 4)`` rigid poses ``world_T_camera``.

    Returns:
        ``(T, 4, 4)`` motions.

    Example:
        >>> step = torch.eye(4).repeat(3, 1, 1); step[:, 2, 3] = -0.1
        >>> torch.allclose(motions_from_poses(compose_motions(step))[1:], step[1:])
        True
    """
    check_shape(poses, ["T", "4", "4"], "poses")
    first = torch.eye(4, dtype=poses.dtype, device=poses.device)[None]
    return torch.cat([first, torch.linalg.solve(poses[1:], poses[:-1])])


def relative_pose_error(est: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    """Relative pose error (RPE) of per-frame motions over consecutive frames, ``t = 0`` skipped.

    Args:
        est: ``(T, 4, 4)`` estimated motions ``camera_t_T_camera_{t-1}``.
        gt: ``(T, 4, 4)`` true motions of the same frames.

    Returns:
        ``{"translation_rmse_m", "translation_median_m", "rotation_mean_deg", "rotation_median_deg"}`` as Python
        floats.

    Example:
        >>> gt = torch.eye(4).repeat(3, 1, 1); est = gt.clone(); est[2, 0, 3] = 0.2
        >>> relative_pose_error(est, gt)["translation_median_m"]  # errors 0 and 0.2 m
        0.0
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
    """Absolute trajectory error (ATE): RMSE in metres of camera positions after a rigid alignment onto ``gt``.

    The alignment is the least-squares rotation and translation (Kabsch/Umeyama without scale: a stereo rig measures
    metric scale, so scale is not fitted away).

    Args:
        est_poses: ``(T, 4, 4)`` estimated poses ``world_T_camera``.
        gt_poses: ``(T, 4, 4)`` true poses of the same frames.
        align: fit the rigid alignment first (default: the estimate's world frame is arbitrary); False compares the
            raw positions.

    Returns:
        Python float, metres.

    Example:
        >>> gt = torch.eye(4).repeat(3, 1, 1); gt[:, 0, 3] = torch.tensor([0.0, 1.0, 2.0])
        >>> est = gt.clone(); est[:, 1, 3] = 5.0  # the same path, shifted: aligned away
        >>> round(absolute_trajectory_error(est, gt), 6), round(absolute_trajectory_error(est, gt, align=False), 6)
        (0.0, 5.0)
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
