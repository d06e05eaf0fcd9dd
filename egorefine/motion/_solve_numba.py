"""CPU inference path of the whole ego-motion solve (egorefine.motion.solve) compiled with numba.

In the refiner's loop the solve sees one frame of a few hundred features per call. The torch path
spends its time on it in about 250 operator launches (sampling the disparity at the features, the
rows of equation (2), the batched RANSAC with its refit, the start motion, the LM, the SE(3) log
and the quality flag), while the arithmetic is a few hundred thousand multiply-adds. Here one
compiled call does all of it for every batch item: the input value checks, the disparity sampling
with its usability rules, the motion-field rows (docs/method.md eq. 2), then per method

* ``"exact"``: the MSAC RANSAC over minimal sets of 3 features and its refit by the normal equations
  of eq. (3), the start motion, the LM of :mod:`egorefine.motion._lm_numba`
  (:func:`~egorefine.motion._lm_numba.lm_item`) and the twist by the SE(3) log;
* ``"robust"``: the RANSAC with its three fits on the inliers, the motion by the SE(3) exp;
* ``"linear"``: the weighted fit of eq. (3) over every usable feature, the motion by the SE(3) exp;

and the weights, RMS and the conditioning test of ``ok``.

The steps are the torch path's, with its random draws (the same ``torch.rand`` tensor, cached per
``(hypotheses, seed, dtype)``), tie-breaking (the first minimal MSAC cost, costs compared as rounded
to the input dtype) and comparisons on the input values (usability of a disparity sample, the RANSAC
index ``floor(u * n)`` in the input dtype); the arithmetic runs in float64 whatever the input dtype,
so a float32 result differs from the torch path's by that path's float32 rounding. An inlier
decision can differ where a residual lies within that rounding of a threshold, and the RANSAC
winner where the torch path's minimal solve is itself rounding noise: a degenerate minimal set (a
feature drawn twice, nearly collinear points) is solved through the damping, 1e-6 of a unit
diagonal, so its float32 solution is far from exact. That happens with few features, rarely, and
not with the hundreds of features the refiner tracks (the rates measured are in docs/decisions.md).

:func:`solve_compiled` returns ``None`` when an input value is bad (NaN in the points or ``K``, a
baseline <= 0, a negative weight, ``K`` not invertible): the caller then runs the torch path,
whose checks raise the documented error. ``AVAILABLE`` is False when numba cannot be imported.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core import eps_like
from ..core._jit import AVAILABLE
from ..core._jit import jit as _jit
from ..geometry.se3 import _SERIES_ANGLE_F64, _SMALL_ANGLE
from . import _lm_numba
from .robust import HUBER_K, TUKEY_C

__all__ = ["AVAILABLE", "solve_compiled"]

# the robust kernels' constants (their codes are _lm_numba's)
_KERNEL = {"l2": 1.0, "huber": HUBER_K, "tukey": TUKEY_C}
# The SE(3) maps run in float64 here: their cancelling coefficients use float64's series range.
_SERIES2 = _SERIES_ANGLE_F64**2

if AVAILABLE:
    from ._lm_numba import _damped_step, _scale, _twist_exp, _weight, lm_item

    @_jit
    def _inputs_bad(pp, pn, K, baseline, weights, has_weights, tiny):
        """The value checks of solve._check_inputs: True if any would fail (the torch path then raises)."""
        B, N = pp.shape[0], pp.shape[1]
        for b in range(B):
            for i in range(N):
                for c in range(2):
                    if not (np.isfinite(pp[b, i, c]) and np.isfinite(pn[b, i, c])):
                        return True
                if has_weights and not (np.isfinite(weights[b, i]) and weights[b, i] >= 0):
                    return True
            k = K[b]
            for r in range(3):
                for c in range(3):
                    if not np.isfinite(k[r, c]):
                        return True
            det = (float(k[0, 0]) * (float(k[1, 1]) * k[2, 2] - float(k[1, 2]) * k[2, 1])
                   - float(k[0, 1]) * (float(k[1, 0]) * k[2, 2] - float(k[1, 2]) * k[2, 0])
                   + float(k[0, 2]) * (float(k[1, 0]) * k[2, 1] - float(k[1, 1]) * k[2, 0]))
            if not (k[0, 0] > 0 and k[1, 1] > 0 and abs(det) > tiny):
                return True
            if not (np.isfinite(baseline[b]) and baseline[b] > 0):
                return True
        return False

    @_jit
    def _sample(pts, disp, valid, has_valid, height, width, spread, out, usable):
        """solve._disparity_at on a map ``disp (H*W,)`` for one item: bilinear samples where usable, else 0.

        The usability tests compare the input values in their own dtype (the spread of the 4 pixels is
        their difference rounded as the torch path rounds it); the interpolation runs in float64."""
        for i in range(pts.shape[0]):
            x, y = pts[i, 0], pts[i, 1]
            inside = x >= 0 and x <= width - 1 and y >= 0 and y <= height - 1
            x0f = min(max(np.floor(x), 0), width - 1)
            y0f = min(max(np.floor(y), 0), height - 1)
            x0, y0 = int(x0f), int(y0f)
            x1, y1 = min(x0 + 1, width - 1), min(y0 + 1, height - 1)
            i00, i01, i10, i11 = y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1
            v00, v01, v10, v11 = disp[i00], disp[i01], disp[i10], disp[i11]
            good = (np.isfinite(v00) and v00 > 0 and np.isfinite(v01) and v01 > 0
                    and np.isfinite(v10) and v10 > 0 and np.isfinite(v11) and v11 > 0)
            if has_valid:
                good = good and valid[i00] and valid[i01] and valid[i10] and valid[i11]
            if not (inside and good):
                out[i], usable[i] = 0.0, False
                continue
            # a blend across a depth edge is a depth that exists nowhere: not used
            if max(max(v00, v01), max(v10, v11)) - min(min(v00, v01), min(v10, v11)) > spread:
                out[i], usable[i] = 0.0, False
                continue
            fx, fy = min(max(float(x) - x0f, 0.0), 1.0), min(max(float(y) - y0f, 0.0), 1.0)
            top = v00 + fx * (float(v01) - v00)
            bottom = v10 + fx * (float(v11) - v10)
            out[i], usable[i] = top + fy * (bottom - top), True

    @_jit
    def _rows(pp, pn, inv_depth, fx, fy, cx, cy, R):
        """Equation (2) per feature as rows ``R (12, N)``: the 5 non-zero entries of du/d(twist) (columns 0, 2-5),
        of dv/d(twist) (columns 1-5), then the tracked displacement ``(bu, bv)`` (see field.motion_field_jacobian)."""
        for i in range(pp.shape[0]):
            xn, yn, z = (pp[i, 0] - cx) / fx, (pp[i, 1] - cy) / fy, inv_depth[i]
            R[0, i], R[1, i], R[2, i] = -fx * z, fx * xn * z, fx * xn * yn
            R[3, i], R[4, i] = -fx * (1 + xn * xn), fx * yn
            R[5, i], R[6, i], R[7, i] = -fy * z, fy * yn * z, fy * (1 + yn * yn)
            R[8, i], R[9, i] = -fy * xn * yn, -fy * xn
            R[10, i], R[11, i] = float(pn[i, 0]) - pp[i, 0], float(pn[i, 1]) - pp[i, 1]

    @_jit(inline="always")
    def _full_rows(R, i, au, av):
        """The 6 entries of both rows of feature ``i``."""
        au[0], au[1], au[2], au[3], au[4], au[5] = R[0, i], 0.0, R[1, i], R[2, i], R[3, i], R[4, i]
        av[0], av[1], av[2], av[3], av[4], av[5] = 0.0, R[5, i], R[6, i], R[7, i], R[8, i], R[9, i]

    @_jit
    def _normal(R, w, H, g):
        """The weighted normal equations of eq. (3): ``H = A^T W A`` and ``g = -A^T W b`` (``_damped_step`` solves
        for ``-g``)."""
        H[:] = 0.0
        g[:] = 0.0
        au, av = np.empty(6), np.empty(6)
        for i in range(R.shape[1]):
            wi = w[i]
            if wi == 0.0:
                continue
            _full_rows(R, i, au, av)
            for a in range(6):
                ua, va = wi * au[a], wi * av[a]
                g[a] -= ua * R[10, i] + va * R[11, i]
                for c in range(a, 6):
                    H[a, c] += ua * au[c] + va * av[c]
        for a in range(6):
            for c in range(a):
                H[a, c] = H[c, a]

    @_jit
    def _fit(R, w, damping, eps, tiny, x):
        """_linear._linear_fit: eq. (3) by the normal equations, Jacobi-scaled and damped, solved into ``x``."""
        H = np.empty((6, 6))
        g = np.empty(6)
        _normal(R, w, H, g)
        _damped_step(H, g, damping, eps, tiny, x)

    @_jit(fastmath={"reassoc", "contract", "nsz"})
    def _residual2(R, x, r2):
        """Squared residual norms ``|A x - b|^2`` per feature (float64; the order of additions is free)."""
        for i in range(R.shape[1]):
            ru = R[0, i] * x[0] + R[1, i] * x[2] + R[2, i] * x[3] + R[3, i] * x[4] + R[4, i] * x[5] - R[10, i]
            rv = R[5, i] * x[1] + R[6, i] * x[2] + R[7, i] * x[3] + R[8, i] * x[4] + R[9, i] * x[5] - R[11, i]
            r2[i] = ru * ru + rv * rv

    @_jit(fastmath={"reassoc", "contract", "nsz"})
    def _msac_cost(r2, w, t2):
        """MSAC: the weighted truncated squared error."""
        total = 0.0
        for i in range(r2.shape[0]):
            total += w[i] * min(r2[i], t2)
        return total

    @_jit
    def _ransac(R, w, u, rounded, threshold, refits, damping, eps, tiny, x, inl):
        """_linear._ransac for one item: MSAC over the minimal sets drawn by ``u (hyp, 3)``, then the refits.

        ``rounded`` is a 2-element array of the input dtype, to round as the torch path rounds: the index
        ``floor(u * n)`` of a draw, and each MSAC cost before it is compared (minimal sets that fit exactly tie in
        the input dtype; in float64 their residuals' rounding noise would pick another one than the torch path).
        ``x`` receives the twist, ``inl`` the inlier flags (weights = ``w * inl``)."""
        N = R.shape[1]
        order = np.empty(N, np.int64)  # valid features first, in their order
        n = 0
        for i in range(N):
            if w[i] > 0:
                order[n] = i
                n += 1
        m = n
        for i in range(N):
            if not w[i] > 0:
                order[m] = i
                m += 1
        rounded[0] = n
        t2 = threshold * threshold
        H = np.empty((6, 6))
        g = np.empty(6)
        X = np.empty(6)
        best_x = np.zeros(6)
        r2 = np.empty(N)
        au, av = np.empty(6), np.empty(6)
        best_cost = np.inf
        for h in range(u.shape[0]):
            H[:] = 0.0
            g[:] = 0.0
            for k in range(3):
                j = min(int(u[h, k] * rounded[0]), max(n - 1, 0))
                i = order[j]
                _full_rows(R, i, au, av)
                for a in range(6):
                    g[a] -= au[a] * R[10, i] + av[a] * R[11, i]
                    for c in range(6):
                        H[a, c] += au[a] * au[c] + av[a] * av[c]
            _damped_step(H, g, damping, eps, tiny, X)
            _residual2(R, X, r2)
            rounded[1] = _msac_cost(r2, w, t2)
            cost = float(rounded[1])
            if h == 0:
                best_x[:] = X
            if cost < best_cost:  # the first minimal cost, as argmin (a NaN cost is never taken)
                best_cost = cost
                best_x[:] = X
        _residual2(R, best_x, r2)
        wi = np.empty(N)
        for i in range(N):
            inl[i] = w[i] > 0 and r2[i] < t2
        for _ in range(refits - 1):
            for i in range(N):
                wi[i] = w[i] if inl[i] else 0.0
            _fit(R, wi, damping, eps, tiny, x)
            _residual2(R, x, r2)
            for i in range(N):
                inl[i] = w[i] > 0 and math.sqrt(r2[i] + tiny) < threshold
        for i in range(N):
            wi[i] = w[i] if inl[i] else 0.0
        _fit(R, wi, damping, eps, tiny, x)

    @_jit
    def _se3_exp(xi, sign, small2, E):
        """geometry.se3_exp of the twist ``sign * xi[:6]`` (translation first; ``sign`` 1 or -1) into ``E (4, 4)``,
        float64, in closed form with its series near zero rotation (``small2``: the squared angle below which
        Rodrigues' terms are series)."""
        p0, p1, p2 = sign * xi[3], sign * xi[4], sign * xi[5]
        t2 = p0 * p0 + p1 * p1 + p2 * p2
        if t2 < small2:
            a = 1 - t2 / 6 + t2 * t2 / 120
            b = 0.5 - t2 / 24 + t2 * t2 / 720
        else:
            t = math.sqrt(t2)
            half = math.sin(0.5 * t) / t
            a, b = math.sin(t) / t, 2 * half * half
        if t2 < _SERIES2:
            c = 1 / 6 - t2 / 120 + t2**2 / 5040 - t2**3 / 362880 + t2**4 / 39916800
        else:
            t = math.sqrt(t2)
            c = (t - math.sin(t)) / (t2 * t)
        W = np.array([[0.0, -p2, p1], [p2, 0.0, -p0], [-p1, p0, 0.0]])
        for r in range(3):
            tr = 0.0
            for col in range(3):
                w2 = W[r, 0] * W[0, col] + W[r, 1] * W[1, col] + W[r, 2] * W[2, col]
                eye = 1.0 if r == col else 0.0
                E[r, col] = eye + a * W[r, col] + b * w2  # Rodrigues
                tr += (eye + b * W[r, col] + c * w2) * (sign * xi[col])  # left Jacobian of SO(3) times translation
            E[r, 3] = tr
        E[3, 0], E[3, 1], E[3, 2], E[3, 3] = 0.0, 0.0, 0.0, 1.0

    @_jit
    def _motion_of(twist, small2, M):
        """twist_to_motion = se3_exp(-twist) (geometry.se3) in closed form, with the same series near zero rotation."""
        _se3_exp(twist, -1.0, small2, M)

    @_jit
    def _twist_of(M, tiny, small2, twist):
        """motion_to_twist = -se3_log (geometry.se3) of one 4x4 motion, with the same series near zero rotation."""
        v0, v1, v2 = M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]
        cos = 0.5 * (M[0, 0] + M[1, 1] + M[2, 2] - 1)
        sin = 0.5 * math.sqrt(max(v0 * v0 + v1 * v1 + v2 * v2, tiny))
        theta = math.atan2(sin, cos)
        t2 = theta * theta
        scale = 1 + t2 / 6 + 7 * t2 * t2 / 360 if t2 < small2 else theta / sin
        if t2 < _SERIES2:
            d = 1 / 12 + t2 / 720 + t2**2 / 30240 + t2**3 / 1209600 + t2**4 / 47900160
        else:
            t = math.sqrt(t2)
            half = math.sin(0.5 * t) / t
            d = (1 - (math.sin(t) / t) / (4 * half * half)) / t2
        p0, p1, p2 = 0.5 * scale * v0, 0.5 * scale * v1, 0.5 * scale * v2
        W = np.array([[0.0, -p2, p1], [p2, 0.0, -p0], [-p1, p0, 0.0]])
        for r in range(3):
            rho = 0.0
            for c in range(3):
                w2 = W[r, 0] * W[0, c] + W[r, 1] * W[1, c] + W[r, 2] * W[2, c]
                rho += ((1.0 if r == c else 0.0) - 0.5 * W[r, c] + d * w2) * M[c, 3]
            twist[r] = -rho
        twist[3], twist[4], twist[5] = -p0, -p1, -p2

    @_jit
    def _solve(pp, pn, disp, is_map, height, width, spread, valid, has_valid, K, baseline, weights, has_weights, u,
               rounded, threshold, method, refits, late_is_w, codes, ks, iters, min_features, rcond, eps, tiny, small2,
               motion, twist, w_out, ok, num, rms):
        """The solve (``method`` 0 exact, 1 robust, 2 linear) of every batch item into the output arrays (the input
        dtype, ok bool, num int64)."""
        B, N = pp.shape[0], pp.shape[1]
        d = np.empty(N)
        usable = np.empty(N, np.bool_)
        w = np.empty(N)
        R = np.empty((12, N))
        x = np.empty(6)
        inl = np.empty(N, np.bool_)
        w_in = np.empty(N)
        rays = np.empty((N, 4))
        target = np.empty((N, 2))
        S = np.empty((N, 16))
        Hs = np.empty((6, 6))
        cam = np.empty(4)
        M = np.empty((4, 4))  # the motion, in float64 whatever the output dtype
        tw = np.empty(6)
        H = np.empty((6, 6))
        g = np.empty(6)
        sc = np.empty(6)
        r2 = np.empty(N)
        for b in range(B):
            fx, fy, cx, cy = float(K[b, 0, 0]), float(K[b, 1, 1]), float(K[b, 0, 2]), float(K[b, 1, 2])
            if is_map:
                _sample(pp[b], disp[b], valid[b if has_valid else 0], has_valid, height, width, spread, d, usable)
            else:
                for i in range(N):
                    usable[i] = np.isfinite(disp[b, i]) and disp[b, i] > 0
                    d[i] = disp[b, i] if usable[i] else 0.0
            fb = fx * baseline[b]
            for i in range(N):
                w[i] = (weights[b, i] if has_weights else 1.0) if usable[i] else 0.0
                d[i] = d[i] / fb  # inverse depth 1/Z = d / (f B)
            _rows(pp[b], pn[b], d, fx, fy, cx, cy, R)
            if method == 2:  # "linear": eq. (3) over every usable feature
                _fit(R, w, eps, eps, tiny, x)
                late = w
            else:
                _ransac(R, w, u, rounded, threshold, refits, eps, eps, tiny, x, inl)
                for i in range(N):
                    w_in[i] = w[i] if inl[i] else 0.0
                late = w if method == 0 and late_is_w else w_in
            # outputs: the final weights (counted as stored, in the output dtype), the RMS of the final model's
            # residuals, the twist and the quality flag
            count, wsum, sq = 0, 0.0, 0.0
            wo = w_out[b]
            if method == 0:  # "exact": the LM from the RANSAC twist, on the reprojection error
                for i in range(N):
                    rays[i, 0], rays[i, 1] = (pp[b, i, 0] - cx) / fx, (pp[b, i, 1] - cy) / fy
                    rays[i, 2], rays[i, 3] = 1.0, d[i]
                    target[i, 0], target[i, 1] = pn[b, i, 0], pn[b, i, 1]
                for a in range(6):  # start: twist_to_motion(twist) = exp(-twist), a non-finite component taken as 0
                    x[a] = -x[a] if np.isfinite(x[a]) else 0.0
                _twist_exp(x, M)
                cam[0], cam[1], cam[2], cam[3] = fx, fy, cx, cy
                lm_item(M, rays, target, cam, w_in, late, codes, ks, iters, eps, tiny, S, Hs)
                for i in range(N):
                    wo[i] = late[i] * S[i, 15] * _weight(S[i, 14], codes[1], ks[1])
                    r = S[i, 14] * S[i, 15]
                    if wo[i] > 0:
                        count += 1
                    wsum += wo[i]
                    sq += wo[i] * r * r
                _twist_of(M, tiny, small2, tw)
            else:  # the linear model's normal matrix and residuals at the final weights
                _normal(R, late, H, g)
                _scale(H, eps, tiny, sc)
                for r in range(6):
                    for c in range(6):
                        Hs[r, c] = H[r, c] * sc[r] * sc[c]
                _residual2(R, x, r2)
                for i in range(N):
                    wo[i] = late[i]
                    if wo[i] > 0:
                        count += 1
                    wsum += wo[i]
                    sq += wo[i] * (r2[i] + tiny)  # _linear._norm2 squared
                tw[:] = x
            rms_b = math.sqrt(sq / max(wsum, eps))
            ev = np.linalg.eigvalsh(Hs)
            finite = np.isfinite(rms_b)
            for a in range(6):
                finite = finite and np.isfinite(tw[a]) and np.isfinite(ev[a])
            good = count >= min_features and ev[0] > rcond * max(ev[5], tiny) and finite
            ok[b] = good
            if good:
                num[b], rms[b] = count, rms_b
                for a in range(6):
                    twist[b, a] = tw[a]
                if method != 0:
                    _motion_of(tw, small2, M)
                for r in range(4):
                    for c in range(4):
                        motion[b, r, c] = M[r, c]
            else:  # fallback: identity, zero twist, no inliers
                num[b], rms[b] = 0, 0.0
                twist[b, :] = 0.0
                wo[:] = 0.0
                motion[b, :, :] = 0.0
                for a in range(4):
                    motion[b, a, a] = 1.0

_DRAWS: dict[tuple[int, int, torch.dtype], np.ndarray] = {}


def _draws(hypotheses: int, seed: int, dtype: torch.dtype) -> np.ndarray:
    """RANSAC's uniform draws ``(hypotheses, 3)``: the torch path's ``torch.rand`` of a generator seeded with
    ``seed`` (shared by all batch items), computed once per ``(hypotheses, seed, dtype)``."""
    key = (hypotheses, seed, dtype)
    if key not in _DRAWS:
        if len(_DRAWS) >= 64:  # a caller that changes the seed on every call must not grow it without bound
            _DRAWS.clear()
        gen = torch.Generator().manual_seed(seed)
        _DRAWS[key] = torch.rand(hypotheses, 3, generator=gen, dtype=dtype).numpy()
    return _DRAWS[key]


def _array(t: torch.Tensor, dtype: np.dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy(), dtype=dtype)


_NO_BOOL = np.zeros((1, 1), np.bool_)


_METHOD_CODES = {"exact": 0, "robust": 1, "linear": 2}


def solve_compiled(
    points_prev: torch.Tensor,
    points_next: torch.Tensor,
    disparity_prev: torch.Tensor,
    K: torch.Tensor,
    baseline: torch.Tensor,
    weights: torch.Tensor | None,
    valid_prev: torch.Tensor | None,
    *,
    method: str,
    refits: int,
    min_features: int,
    loss: str,
    scale: float,
    ransac_hypotheses: int,
    ransac_threshold: float,
    iterations: int,
    seed: int,
    rcond: float,
    max_spread: float,
) -> tuple[torch.Tensor, ...] | None:
    """:func:`~egorefine.motion.solve_ego_motion` for CPU float32/float64 tensors without gradient, compiled.

    Shapes, dtypes and settings must have been checked by the caller (solve.solve_ego_motion); ``refits`` is the
    number of RANSAC fits on the inliers (_linear._REFITS) and ``max_spread`` solve._MAX_DISPARITY_SPREAD, the largest
    disparity difference among the 4 pixels of a usable sample.

    Returns:
        ``(motion (B, 4, 4), twist (B, 6), weights (B, N), ok (B,), num_inliers (B,), rms (B,))`` in the dtype of
        ``points_prev``, or ``None`` if an input value fails the checks of ``solve._check_inputs`` (the torch
        path then raises the documented error).
    """
    dtype = points_prev.dtype
    nd = np.float32 if dtype == torch.float32 else np.float64
    info = torch.finfo(dtype)
    pp, pn = _array(points_prev, nd), _array(points_next, nd)
    B, N = pp.shape[:2]
    Kn, bl = _array(K, nd), _array(baseline, nd)
    wn = _array(weights, nd) if weights is not None else np.ones((1, 1), nd)
    if _inputs_bad(pp, pn, Kn, bl, wn, weights is not None, info.tiny):
        return None
    is_map = disparity_prev.dim() == 4
    height, width = disparity_prev.shape[-2:] if is_map else (1, 1)
    disp = _array(disparity_prev.reshape(B, -1), nd)
    valid = _NO_BOOL if valid_prev is None else _array(valid_prev.reshape(B, -1), np.bool_)
    codes = np.array([_lm_numba._LOSS_CODES["huber"], _lm_numba._LOSS_CODES[loss]], np.int64)
    ks = np.array([_KERNEL["huber"] * scale, _KERNEL[loss] * scale])
    first = iterations // 2
    motion, twist, w_out, rms = (torch.empty(shape, dtype=dtype) for shape in ((B, 4, 4), (B, 6), (B, N), (B,)))
    ok, num = torch.empty(B, dtype=torch.bool), torch.empty(B, dtype=torch.long)
    if N > 0:
        _solve(pp, pn, disp, is_map, height, width, float(max_spread), valid, valid_prev is not None, Kn, bl, wn,
               weights is not None, _draws(ransac_hypotheses, seed, dtype), np.empty(2, nd), float(ransac_threshold),
               _METHOD_CODES[method], int(refits), loss == "tukey", codes, ks,
               np.array([first, iterations - first], np.int64), int(min_features), float(rcond), eps_like(points_prev),
               info.tiny, _SMALL_ANGLE**2, motion.numpy(), twist.numpy(), w_out.numpy(), ok.numpy(), num.numpy(),
               rms.numpy())
    else:  # no features: the fallback of every item
        motion[:] = torch.eye(4, dtype=dtype)
        for t in (twist, rms, ok, num):
            t.zero_()
    return motion, twist, w_out, ok, num, rms
