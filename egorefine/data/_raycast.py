"""Ray casting of box scenes (:mod:`egorefine.data._world`): every face scan-converted with exact per-pixel depth
(a w-buffer), shaded with band-limited textures and Lambertian lights, pixels on geometric edges supersampled.

One view at a time, on the render device; :mod:`egorefine.data.synthetic` renders the stereo pairs of a sequence
with it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._families import FAMILY_NAMES, FAMILY_TEXEL, family_textures
from ._texture import make_texture
from ._world import RigPreset, _Box


def _faces(boxes: list[_Box]) -> dict[str, np.ndarray]:
    """Every box face as a rectangle facing its visible side: centre, unit normal, in-plane axes, half sizes.

    Face ``6 b + 2 k + (side > 0)`` is the face of box ``b`` normal to its axis ``k``. Normals point out of solid
    boxes and into the room, so a face can be seen only from the side its normal points to.
    """
    other = ((1, 2), (0, 2), (0, 1))
    centre, normal, eu, ev, half = [], [], [], [], []
    for b in boxes:
        for k in range(3):
            for side in (-1.0, 1.0):
                i, j = other[k]
                centre.append(b.centre + side * b.half[k] * b.rot[:, k])
                normal.append((-side if b.inside else side) * b.rot[:, k])
                eu.append(b.rot[:, i])
                ev.append(b.rot[:, j])
                half.append((b.half[i], b.half[j]))
    return {k: np.asarray(v, dtype=np.float64) for k, v in
            (("centre", centre), ("normal", normal), ("eu", eu), ("ev", ev), ("half", half))}


class _Renderer:
    """Scan-converts box faces with exact per-pixel depth (a w-buffer) and shades them (all on the render device).

    For a planar face, inverse depth ``1 / Z`` and ``u / Z``, ``v / Z`` (in-plane coordinates over depth) are affine
    functions of the pixel coordinates, so intersecting every pixel's ray with a face costs a few multiply-adds
    per pixel, evaluated only inside the face's projected bounding rectangle.
    """

    def __init__(self, boxes: list[_Box], lights: np.ndarray, preset: RigPreset, K: np.ndarray,
                 height: int, width: int, rng: np.random.Generator, texture_seed: int,
                 device: torch.device, dtype: torch.dtype, families: np.ndarray | None = None,
                 family_rng: np.random.Generator | None = None) -> None:
        self.device, self.dtype = device, dtype
        self.h, self.w = height, width
        self.f, self.cx, self.cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
        self.scale = preset.scale
        self.np_faces = _faces(boxes)
        n_faces = len(self.np_faces["centre"])

        def t(x: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x), device=device, dtype=dtype)

        self.face_centre = t(self.np_faces["centre"])
        self.face_normal = t(self.np_faces["normal"])
        self.face_eu = t(self.np_faces["eu"])
        self.face_ev = t(self.np_faces["ev"])
        ang = rng.uniform(0, 2 * math.pi, n_faces)
        scl = rng.uniform(0.75, 1.35, n_faces) * preset.texel
        off = rng.uniform(0, 4096, (n_faces, 2))
        gain = rng.uniform(0.9, 1.25, n_faces)
        bias = rng.uniform(-0.05, 0.05, n_faces)
        self.families = None
        if families is not None:
            ang, scl, gain, bias = self._family_layout(families, ang, scl, gain, bias, family_rng)
            self.families = family_textures(str(device), dtype)
            self.face_family = torch.as_tensor(families, device=device)
        # Texel coordinates = A_f @ (u, v) + off_f, A_f a rotation over the face's texel size.
        A = np.stack([np.cos(ang), -np.sin(ang), np.sin(ang), np.cos(ang)], -1).reshape(-1, 2, 2) / scl[:, None, None]
        self.face_A = t(A)
        self.face_off = t(off)
        self.face_texel = t(scl)
        self.face_gain = t(gain)
        self.face_bias = t(bias)
        # A directional light (the sun outdoors, a window indoors): constant over each planar face.
        sun = np.array([0.4, -0.8, 0.45])
        sun_term = np.clip(self.np_faces["normal"] @ (sun / np.linalg.norm(sun)), 0.0, None)
        self.face_sun = t(sun_term)
        self.sun_weight = 0.45 if len(lights) == 0 else 0.15
        self.lights = t(lights)
        self.light_range = 4.0 * preset.scale
        self.texture = make_texture(texture_seed, device=str(device), dtype=dtype)
        self.xs = torch.arange(width, device=device, dtype=dtype)
        self.ys = torch.arange(height, device=device, dtype=dtype)

    def _family_layout(self, families: np.ndarray, ang: np.ndarray, scl: np.ndarray, gain: np.ndarray,
                       bias: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
        """Placement of the texture families: periodic patterns upright at their physical size, a bright sky."""
        ang, scl, gain, bias = ang.copy(), scl.copy(), gain.copy(), bias.copy()
        jitter = rng.uniform(0.9, 1.1, len(families))
        # Rows of a pattern run along the face's more horizontal axis (world y is vertical).
        eu_up = np.abs(self.np_faces["eu"][:, 1]) > np.abs(self.np_faces["ev"][:, 1])
        for k, name in enumerate(FAMILY_NAMES):  # loop over a handful of families
            on = families == k
            if FAMILY_TEXEL[name] is not None:
                ang[on] = np.where(eu_up[on], 0.5 * math.pi, 0.0)
                scl[on] = FAMILY_TEXEL[name] * jitter[on]
            if name == "sky":  # unlit by the lamps and the sun: bright on its own
                gain[on], bias[on] = 1.6, 0.0
        return ang, scl, gain, bias

    # -- per camera: affine coefficients and bounding rectangles of the faces

    def setup(self, world_T_cam: np.ndarray) -> list[tuple[int, tuple, int, int, int, int]]:
        """Visible faces for a camera: ``(face, coefficients, x0, x1, y0, y1)`` with half-open pixel rectangles.

        ``coefficients`` are three affine maps ``(a_x, a_y, c)`` of the pixel coordinates: ``1 / Z``, ``u / Z`` and
        ``v / Z`` along each pixel's ray, and the face's half sizes ``(h_u, h_v)``.
        """
        R, o = world_T_cam[:3, :3], world_T_cam[:3, 3]
        F = self.np_faces
        rel = F["centre"] - o  # (F, 3)
        dist = (rel * F["normal"]).sum(-1)  # < 0 when the camera is on the face's visible side
        near = 1e-3 * self.scale
        f, cx, cy = self.f, self.cx, self.cy
        out = []
        corners_uv = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        for i in np.nonzero(dist < -1e-9 * self.scale)[0]:  # loop over front-facing faces
            # Clip the face rectangle to the near plane, then bound its projection.
            corners = F["centre"][i] + (corners_uv * F["half"][i]) @ np.stack([F["eu"][i], F["ev"][i]])
            cam = (corners - o) @ R
            poly = []
            for a, b in zip(cam, np.roll(cam, -1, axis=0), strict=True):
                if a[2] >= near:
                    poly.append(a)
                if (a[2] >= near) != (b[2] >= near):
                    poly.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
            if not poly:
                continue
            poly = np.asarray(poly)
            x = f * poly[:, 0] / poly[:, 2] + cx
            y = f * poly[:, 1] / poly[:, 2] + cy
            x0, x1 = max(math.floor(x.min()) - 1, 0), min(math.ceil(x.max()) + 2, self.w)
            y0, y1 = max(math.floor(y.min()) - 1, 0), min(math.ceil(y.max()) + 2, self.h)
            if x0 >= x1 or y0 >= y1:
                continue

            def affine(w: np.ndarray) -> np.ndarray:
                # w . d(x, y) with d = R [(x - cx) / f, (y - cy) / f, 1]: affine in (x, y).
                m = R.T @ w
                return np.array([m[0] / f, m[1] / f, m[2] - m[0] * cx / f - m[1] * cy / f])

            inv = affine(F["normal"][i]) / dist[i]  # 1 / t = (n . d) / ((p0 - o) . n)
            u = -(rel[i] @ F["eu"][i]) * inv + affine(F["eu"][i])  # u / t = (o - p0) . e_u / t + e_u . d
            v = -(rel[i] @ F["ev"][i]) * inv + affine(F["ev"][i])
            coef = (*inv.tolist(), *u.tolist(), *v.tolist(), float(F["half"][i][0]), float(F["half"][i][1]))
            out.append((int(i), coef, x0, x1, y0, y1))
        return out

    @staticmethod
    def _inv_depth(coef: tuple, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Inverse depth of the face along the rays through pixels ``(x, y)`` (broadcast); 0 where they miss it."""
        ia, ib, ic, ua, ub, uc, va, vb, vc, hu, hv = coef
        inv = x * ia + (y * ib + ic)
        # Faces are grown by a hair (relative 1e-5) so that rays through shared edges never slip between them.
        hu, hv = hu * (1.0 + 1e-5), hv * (1.0 + 1e-5)
        inside = ((x * ua + (y * ub + uc)).abs() <= inv * hu) & ((x * va + (y * vb + vc)).abs() <= inv * hv)
        return torch.where(inside & (inv > 0), inv, torch.zeros_like(inv))

    def cast_grid(self, faces: list) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest face for every pixel centre: inverse depth ``(H, W)`` and face index ``(H, W)``."""
        best = torch.zeros((self.h, self.w), device=self.device, dtype=self.dtype)
        ids = torch.zeros((self.h, self.w), device=self.device, dtype=torch.long)
        for i, coef, x0, x1, y0, y1 in faces:  # loop over faces
            inv = self._inv_depth(coef, self.xs[None, x0:x1], self.ys[y0:y1, None])
            cur = best[y0:y1, x0:x1]
            closer = inv > cur
            best[y0:y1, x0:x1] = torch.where(closer, inv, cur)
            ids[y0:y1, x0:x1].masked_fill_(closer, i)
        return best, ids

    def _supersample(self, faces: list, face: torch.Tensor, idx: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Four rotated-grid samples in each pixel ``idx`` ``(n,)`` (flat indices), tested only against the faces
        seen at the centres of the pixel's 3x3 neighbourhood: sample x, y, inverse depth, face, each ``(4 n,)``."""
        n_all = len(self.np_faces["centre"])
        table = torch.zeros((n_all, 11), device=self.device, dtype=self.dtype)
        table[torch.tensor([fc[0] for fc in faces], device=self.device)] = torch.tensor(
            [fc[1] for fc in faces], device=self.device, dtype=self.dtype)
        padded = torch.nn.functional.pad(face[None, None].to(self.dtype), (1, 1, 1, 1), mode="replicate")[0, 0]
        padded = padded.long()
        y, x = idx // self.w, idx % self.w
        cand = torch.stack([padded[y + dy, x + dx] for dy in range(3) for dx in range(3)], -1)  # (n, 9)
        coef = table[cand]  # (n, 9, 11)
        off = torch.tensor([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]],
                           device=self.device, dtype=self.dtype)
        px = x.to(self.dtype)[:, None] + off[:, 0]  # (n, 4)
        py = y.to(self.dtype)[:, None] + off[:, 1]
        X, Y = px[:, :, None], py[:, :, None]  # (n, 4, 1) against coefficients (n, 1, 9)
        c = coef[:, None]
        inv = X * c[..., 0] + Y * c[..., 1] + c[..., 2]
        inside = ((X * c[..., 3] + Y * c[..., 4] + c[..., 5]).abs() <= inv * c[..., 9]) & (
            (X * c[..., 6] + Y * c[..., 7] + c[..., 8]).abs() <= inv * c[..., 10]) & (inv > 0)
        inv = torch.where(inside, inv, torch.zeros_like(inv))
        best, arg = inv.max(-1)  # (n, 4)
        hit = cand.gather(1, arg)  # (n, 4)
        # A sample that none of the neighbourhood's faces covers (a sliver thinner than a pixel) keeps the centre.
        centre = face.view(-1)[idx][:, None].expand(-1, 4)
        inv_centre = 1.0 / self.depth_flat[idx][:, None].expand(-1, 4)
        miss = best <= 0
        hit = torch.where(miss, centre, hit)
        best = torch.where(miss, inv_centre, best)
        return px.reshape(-1), py.reshape(-1), best.reshape(-1), hit.reshape(-1)

    def blocked(self, faces: list, x: torch.Tensor, inv_point: torch.Tensor) -> torch.Tensor:
        """For rays through ``(x[r, c], r)`` ``(H, W)``: does any face lie nearer than ``1 / inv_point``?"""
        limit = inv_point * (1.0 + 1e-4)
        out = torch.zeros(x.shape, device=self.device, dtype=torch.bool)
        for _, coef, x0, _x1, y0, y1 in faces:  # loop over faces; left x >= right x >= x0
            inv = self._inv_depth(coef, x[y0:y1, x0:], self.ys[y0:y1, None])
            out[y0:y1, x0:] |= inv > limit[y0:y1, x0:]
        return out

    # -- shading

    def shade(self, origin: torch.Tensor, dirs: torch.Tensor, depth: torch.Tensor, face: torch.Tensor,
              supersample: float = 1.0) -> torch.Tensor:
        """Intensity ``(n,)`` of hits ``origin + depth * dirs`` on ``face`` (``dirs`` ``(n, 3)``, camera z = 1)."""
        pts = origin + depth[:, None] * dirs
        rel = pts - self.face_centre[face]
        uv = torch.stack([(rel * self.face_eu[face]).sum(-1), (rel * self.face_ev[face]).sum(-1)], -1)
        tex_uv = (self.face_A[face] @ uv[:, :, None])[:, :, 0] + self.face_off[face]
        normal = self.face_normal[face]
        # Footprint of a pixel on the surface (geometric mean of its two axes) in texels: band-limits the texture.
        cos = (normal * dirs).sum(-1).abs() / dirs.norm(dim=-1)
        footprint = depth / (self.f * supersample * cos.clamp_min(1e-3).sqrt()) / self.face_texel[face]
        if self.families is None:
            albedo = self.texture.sample(tex_uv[:, 0], tex_uv[:, 1], footprint)
        else:
            family = self.face_family[face]
            albedo = torch.empty_like(depth)
            for k, tex in enumerate(self.families):  # loop over a handful of texture families
                idx = (family == k).nonzero().squeeze(1)
                if idx.numel() > 0:
                    albedo[idx] = tex.sample(tex_uv[idx, 0], tex_uv[idx, 1], footprint[idx])
        # Lambertian lighting from fixed point lights (view-independent, so left and right agree).
        irradiance = torch.zeros_like(depth)
        for light in self.lights:  # loop over a handful of lights
            to_light = light - pts
            r2 = (to_light * to_light).sum(-1)
            lam = ((to_light * normal).sum(-1) * r2.rsqrt()).clamp_min(0.0)
            irradiance += lam / (1.0 + r2 / self.light_range**2)
        shading = 0.55 + 0.45 * (1.0 - torch.exp(-1.5 * irradiance)) + self.sun_weight * self.face_sun[face]
        value = albedo * shading.clamp_max(1.0) * self.face_gain[face] + self.face_bias[face]
        return value.clamp(0.02, 0.98)

    def _dirs(self, R: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        cam = torch.stack([(x - self.cx) / self.f, (y - self.cy) / self.f, torch.ones_like(x)], -1)
        return cam @ R.T

    # -- one image

    def render_view(self, cam_T: np.ndarray, antialias: bool) -> tuple[torch.Tensor, torch.Tensor, list]:
        """Image ``(H, W)``, depth ``(H, W)`` and visible-face list seen from camera pose ``cam_T`` (world_T_cam)."""
        R = torch.as_tensor(cam_T[:3, :3], device=self.device, dtype=self.dtype)
        origin = torch.as_tensor(cam_T[:3, 3], device=self.device, dtype=self.dtype)
        faces = self.setup(cam_T)
        inv, face = self.cast_grid(faces)
        depth = 1.0 / inv  # every pixel sees a face of the room at least, so inv > 0
        self.depth_flat = depth.view(-1)
        yy, xx = torch.meshgrid(self.ys, self.xs, indexing="ij")
        dirs = self._dirs(R, xx.reshape(-1), yy.reshape(-1))
        value = self.shade(origin, dirs, depth.view(-1), face.view(-1)).view(self.h, self.w)
        if antialias:
            # Re-render pixels on geometric edges (where the face changes) with 4 rotated-grid samples.
            edge = torch.zeros_like(face, dtype=torch.bool)
            dx = face[:, 1:] != face[:, :-1]
            dy = face[1:, :] != face[:-1, :]
            edge[:, 1:] |= dx
            edge[:, :-1] |= dx
            edge[1:, :] |= dy
            edge[:-1, :] |= dy
            idx = edge.view(-1).nonzero().squeeze(1)
            if idx.numel() > 0:
                px, py, inv_s, face_s = self._supersample(faces, face, idx)
                dirs_s = self._dirs(R, px, py)
                vs = self.shade(origin, dirs_s, 1.0 / inv_s, face_s, supersample=2.0)
                value.view(-1)[idx] = vs.view(-1, 4).mean(-1)
        return value, depth, faces
