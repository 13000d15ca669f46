"""Pixel-level bench (docs/design.md §9, level 2): the simulated yard rendered into omni images.

Every pixel of the camera's mirror annulus has a fixed ray in the body frame (the camera is
rigidly mounted: ``R_bc · lift(u, v)``, docs/design.md §6), computed once. A frame from a planar
pose (x, y, ψ in the simulator's map frame, camera ``h`` above flat ground) is then:

* **ground** — rays below the horizon meet the ground at a body-frame offset fixed per pixel;
  rotated and shifted by the pose they index a procedural texture of the yard (grass inside
  the lawn, a lighter path outside, a soft edge). The texture is mip-mapped and each pixel
  reads the level that matches its footprint on the ground, so the far field does not alias
  into flickering false corners;
* **sky** — rays above the horizon index a panorama at infinity (a smooth sky gradient over a
  soft distant tree line) by world azimuth and elevation;
* **landmarks** — each map landmark is a flat, double-sided 0.8 m square panel in a vertical
  plane (a window, a sign on a fence, a board on a post) centred on the landmark point and
  turned towards the lawn: 2×2 dark and light panes (greys of its own), whose centre is an
  X-corner exactly at the landmark point. Panels are ray-cast per pixel
  (not approximated by an affine warp), and a pixel's share of its panel is its hit point's
  distance inside the outline over its footprint, so every corner on a panel — the outline's
  too, near or far — is a fixed 3-D point;
* **optics and sensor** — a little Gaussian blur, then Gaussian pixel noise; black outside
  the annulus.

The ground truth the evaluation needs is kept: :meth:`OmniRenderer.landmark_pixels` (the
exact projection of each landmark point), and :meth:`OmniRenderer.true_points`, the 3-D point
that a pixel sees (ray cast against panels and ground), to score tracks and associations.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from mowerhw.camera import OmniRadtanCamera
from mowerhw.common.geometry import quat_to_rotmat, yaw_rotation
from mowerhw.sim.world import World

FloatArray = NDArray[np.float64]

PANEL_SIZE_M = 0.8
PANEL_TEXELS = 256  # texels across a panel (level 0)
GROUND_TEXEL_M = 0.02
GROUND_LEVELS = 7  # 2 cm … 1.28 m texels
GROUND_MAX_RANGE_M = 60.0
PANO_WIDTH = 3600  # 0.1° per column
PANO_TOP_DEG = 60.0
PANO_BOTTOM_DEG = -3.0
PANO_RES_DEG = 0.1
TRUTH_TOLERANCE_PX = 1.5


@dataclass(frozen=True)
class RenderSettings:
    noise_sigma: float = 2.0  # grey levels (1σ), per pixel per frame
    blur_sigma_px: float = 0.7
    min_panel_cos: float = 0.12  # panels seen more edge-on than ~83° are not drawn


@dataclass(frozen=True)
class Panel:
    """A landmark's panel: centre (map frame, z above ground), unit normal, in-plane axes."""

    center: FloatArray
    normal: FloatArray
    e1: FloatArray  # horizontal, in the plane
    e2: FloatArray  # up
    size: float


class _RayTable:
    """Per-pixel body-frame rays of a camera and what is constant about them."""

    def __init__(self, camera: OmniRadtanCamera, q_bc: tuple[float, ...]) -> None:
        h, w = camera.height, camera.width
        v, u = np.mgrid[0:h, 0:w]
        pix = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        valid = camera.valid(pix)
        rays = np.full((h * w, 3), np.nan, dtype=np.float64)
        rays[valid] = camera.lift(pix[valid]) @ quat_to_rotmat(np.asarray(q_bc)).T
        self.shape = (h, w)
        self.valid = valid.reshape(h, w)
        self.rays = rays.reshape(h, w, 3).astype(np.float32)  # body frame
        # angular size of a pixel (rad), for mip levels: angle to the right-hand neighbour
        r = rays.reshape(h, w, 3)
        dot = np.einsum("ijk,ijk->ij", r[:, :-1], r[:, 1:])
        ang = np.arccos(np.clip(dot, -1.0, 1.0))
        ang = np.concatenate([ang, ang[:, -1:]], axis=1)
        fill = float(np.nanmedian(ang))  # at the mask's rim the neighbour sees nothing
        self.pixel_angle = np.where(np.isfinite(ang), ang, fill).astype(np.float32)
        flat = np.flatnonzero(valid)
        fr = rays[flat]
        self.flat = flat
        self.elevation = np.arcsin(np.clip(fr[:, 2], -1.0, 1.0))
        self.azimuth = np.arctan2(fr[:, 1], fr[:, 0])
        self.flat_rays = fr


@functools.lru_cache(maxsize=4)
def _ray_table(camera: OmniRadtanCamera, q_bc: tuple[float, ...]) -> _RayTable:
    return _RayTable(camera, q_bc)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> FloatArray:
    """Zero-mean, unit-σ Gaussian noise smoothed at ``sigma_px`` (band-limited texture)."""
    n = rng.standard_normal(shape).astype(np.float32)
    if sigma_px > 0.3:
        n = cv2.GaussianBlur(n, (0, 0), sigma_px)
    return n / max(float(n.std()), 1e-6)


def _panel_texture(rng: np.random.Generator) -> NDArray[np.uint8]:
    """A board of 2×2 panes, the dark and light ones on the diagonals so the centre is an
    X-corner; each board has its own greys. Its corners (the centre, the board's corners,
    where the pane edges meet the board's edge) are ≥ 0.4 m apart, so no two of them merge
    into one blob at the far side of a lawn (a frame a few cm wide would put two corners
    7 cm apart: a front end cannot tell them apart at 10 m, and neither could a person)."""
    n = PANEL_TEXELS
    dark, light = rng.uniform(20, 80), rng.uniform(170, 235)
    half = n // 2
    img = np.full((n, n), light)
    if rng.random() < 0.5:
        img[:half, :half] = img[half:, half:] = dark
    else:
        img[:half, half:] = img[half:, :half] = dark
    return img.astype(np.uint8)


_BLOCK = 1024  # cv2.remap wants maps narrower than 32767: pixel lists are folded into rows


def _fold(a: NDArray, fill: float = -10.0) -> NDArray[np.float32]:
    """A 1-D pixel list as a (rows, _BLOCK) float32 map, padded with ``fill``."""
    n = a.size
    out = np.full(-(-n // _BLOCK) * _BLOCK, fill, dtype=np.float32)
    out[:n] = a
    return out.reshape(-1, _BLOCK)


def _mip(img: NDArray, levels: int) -> list[NDArray]:
    out = [img]
    for _ in range(levels - 1):
        if min(out[-1].shape[:2]) < 4:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def _panel_cover(
    a: NDArray[np.floating], b: NDArray[np.floating], size: float, footprint_texels: float
) -> NDArray[np.float32]:
    """How much of each pixel a panel covers: its hit point's distance inside the panel's
    outline (``a``, ``b`` from the centre along the panel's axes, m) over the pixel's
    footprint, so the outline's half-covered pixels lie on the outline at every distance.
    (A coverage mask mip-mapped with the texture drew the outline up to 2^(L−1) texels off
    at level L — a panel's right and lower edges ~1 cm in, its left and upper edges out,
    the far levels most: the outline's corners were no fixed 3-D points; issue 18, stop 75.)"""
    half = np.float32(size / 2)
    inside = np.minimum(half - np.abs(a), half - np.abs(b))  # m; negative outside
    width = np.float32(max(footprint_texels, 1.0) * size / PANEL_TEXELS)
    cover = np.clip(inside / width + np.float32(0.5), 0.0, 1.0).astype(np.float32, copy=False)
    return cover


class OmniRenderer:
    """Renders a :class:`World` through its omni camera (see the module doc)."""

    def __init__(self, world: World, seed: int = 0, settings: RenderSettings | None = None) -> None:
        self.world = world
        self.camera = world.camera
        self.settings = settings or RenderSettings()
        self.height_m = world.scenario.camera_height_m
        self.table = _ray_table(world.camera, tuple(float(x) for x in world.q_bc))
        self._noise_seed = int(np.random.default_rng([seed, 40]).integers(1 << 30))
        self._frames = 0
        tex_rng = np.random.default_rng([seed, 41])
        self._build_ground(tex_rng)
        self._build_sky(tex_rng)
        self._build_panels(tex_rng)
        self._prepare_pixels()

    # ------------------------------------------------------------------------ scene build

    def _build_ground(self, rng: np.random.Generator) -> None:
        outline = self.world.lawn.outline(1440)
        lo = outline.min(axis=0) - 14.0
        hi = outline.max(axis=0) + 14.0
        n = np.ceil((hi - lo) / GROUND_TEXEL_M).astype(int)
        self.ground_origin = lo
        w, h = int(n[0]), int(n[1])
        lawn_mask = np.zeros((h, w), np.uint8)
        pts = np.round((outline - lo) / GROUND_TEXEL_M * 8).astype(np.int32)
        cv2.fillPoly(lawn_mask, [pts.reshape(-1, 1, 2)], 255, lineType=cv2.LINE_AA, shift=3)
        inside = cv2.GaussianBlur(lawn_mask.astype(np.float32) / 255.0, (0, 0), 2.5)
        # grass: fine blades (4 cm) and patches (0.6 m), low contrast; path: sandier, smoother
        fine = _smooth_noise(rng, (h, w), 1.0)
        patches = _smooth_noise(rng, (h, w), 30.0)
        grass = 92.0 + 7.0 * fine + 9.0 * patches
        path = 150.0 + 4.0 * _smooth_noise(rng, (h, w), 1.5) + 6.0 * patches
        tex = inside * grass + (1.0 - inside) * path
        self.ground_mean = float(tex.mean())
        self.ground_mip = [
            np.clip(t, 0, 255).astype(np.float32) for t in _mip(tex.astype(np.float32), 7)
        ]

    def _build_sky(self, rng: np.random.Generator) -> None:
        rows = round((PANO_TOP_DEG - PANO_BOTTOM_DEG) / PANO_RES_DEG)
        elev = PANO_TOP_DEG - (np.arange(rows) + 0.5) * PANO_RES_DEG  # degrees, per row
        az = np.arange(PANO_WIDTH) * (2 * math.pi / PANO_WIDTH)
        line = 6.0 + sum(
            rng.uniform(0.5, 2.0) * np.sin(k * az + rng.uniform(0, 2 * math.pi))
            for k in (1, 2, 3, 5)
        )
        sky = 205.0 + 0.6 * np.clip(elev, 0, None)[:, None] + np.zeros((rows, PANO_WIDTH))
        trees = 70.0 + 6.0 * _smooth_noise(rng, (rows, PANO_WIDTH), 6.0)
        edge = np.clip((line[None, :] - elev[:, None]) / 0.6 + 0.5, 0.0, 1.0)
        pano = edge * trees + (1.0 - edge) * sky
        haze = np.clip((0.0 - elev) / 3.0, 0.0, 1.0)[:, None]  # below the horizon: far ground
        pano = haze * self.ground_mean + (1 - haze) * pano
        self.pano = cv2.GaussianBlur(pano.astype(np.float32), (0, 0), 1.0)

    def _build_panels(self, rng: np.random.Generator) -> None:
        lm = self.world.landmarks_map
        centroid = self.world.lawn.outline(360).mean(axis=0)
        panels, textures = [], []
        twin_of = self.world.twin_of
        for k in range(lm.shape[0]):
            j = -1 if twin_of is None else int(twin_of[k])
            if j >= 0:  # a look-alike: the same panel, turned half round the lawn's centre
                p = panels[j]
                turn = np.array([-1.0, -1.0, 1.0])
                panels.append(
                    Panel(lm[k].astype(np.float64), p.normal * turn, p.e1 * turn, p.e2, p.size)
                )
                textures.append(textures[j])
                continue
            to_lawn = centroid - lm[k, :2]
            yaw = math.atan2(to_lawn[1], to_lawn[0]) + rng.uniform(-0.5, 0.5)
            if np.linalg.norm(to_lawn) < 1.0:
                yaw = rng.uniform(-math.pi, math.pi)
            normal = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            e1 = np.array([-normal[1], normal[0], 0.0])
            panels.append(
                Panel(lm[k].astype(np.float64), normal, e1, np.array([0, 0, 1.0]), PANEL_SIZE_M)
            )
            textures.append(_mip(_panel_texture(rng).astype(np.float32), 6))
        self.panels = panels
        self.panel_mip = textures

    def _prepare_pixels(self) -> None:
        t = self.table
        h = self.height_m
        elev = t.elevation
        ground = elev < -math.atan2(h, GROUND_MAX_RANGE_M)
        rays = t.flat_rays[ground]
        s = h / -rays[:, 2]
        a, b = rays[:, 0] * s, rays[:, 1] * s
        # footprint on the ground along the range direction: range² / h × pixel angle
        rng_m = np.hypot(a, b)
        ang = t.pixel_angle.ravel()[t.flat[ground]]
        foot = (rng_m**2 + h**2) / h * ang
        level = np.clip(
            np.floor(np.log2(np.maximum(foot / GROUND_TEXEL_M, 1.0))), 0, len(self.ground_mip) - 1
        ).astype(int)
        self._ground = []
        for lv in range(len(self.ground_mip)):
            sel = level == lv
            if sel.any():
                self._ground.append((lv, t.flat[ground][sel], _fold(a[sel]), _fold(b[sel])))
        sky = ~ground
        self._sky_idx = t.flat[sky]
        self._sky_col = _fold(t.azimuth[sky] % (2 * math.pi) * (PANO_WIDTH / (2 * math.pi)))
        self._sky_row = _fold((PANO_TOP_DEG - np.degrees(t.elevation[sky])) / PANO_RES_DEG - 0.5)

    # ----------------------------------------------------------------------------- frames

    def render(self, x: float, y: float, yaw: float, noise: bool = True) -> NDArray[np.uint8]:
        """The 8-bit image seen from map-frame pose (x, y, ψ), camera ``h`` above ground."""
        hh, ww = self.table.shape
        img = np.zeros(hh * ww, np.float32)
        c, s = math.cos(yaw), math.sin(yaw)
        ox, oy = self.ground_origin
        for lv, idx, a, b in self._ground:
            # level-L texel k is centred on level-0 texel 2^L·k (cv2.pyrDown)
            res = GROUND_TEXEL_M * 2**lv
            k = 1.0 / 2**lv
            mx = (c / res) * a - (s / res) * b + np.float32(((x - ox) / GROUND_TEXEL_M - 0.5) * k)
            my = (s / res) * a + (c / res) * b + np.float32(((y - oy) / GROUND_TEXEL_M - 0.5) * k)
            img[idx] = cv2.remap(
                self.ground_mip[lv],
                mx,
                my,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=self.ground_mean,
            ).ravel()[: idx.size]
        col = self._sky_col + np.float32(yaw % (2 * math.pi) * PANO_WIDTH / (2 * math.pi))
        col = np.where(col >= PANO_WIDTH, col - PANO_WIDTH, col)
        img[self._sky_idx] = cv2.remap(
            self.pano, col, self._sky_row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        ).ravel()[: self._sky_idx.size]
        img = img.reshape(hh, ww)
        self._draw_panels(img, x, y, yaw)
        st = self.settings
        if st.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), st.blur_sigma_px)
        if noise and st.noise_sigma > 0:
            n = np.empty((hh, ww), np.float32)
            # OpenCV's generator (fast) seeded per frame, so a run is repeatable
            cv2.setRNGSeed(self._noise_seed + self._frames)
            self._frames += 1
            cv2.randn(n, 0.0, st.noise_sigma)
            img += n
        img[~self.table.valid] = 0.0
        return np.clip(img, 0, 255).astype(np.uint8)

    def _camera_center(self, x: float, y: float) -> FloatArray:
        return np.array([x, y, self.height_m])

    def _to_body(self, yaw: float) -> FloatArray:
        """R_bm: map-frame vectors into the body frame (planar pose)."""
        return yaw_rotation(yaw).T

    def _project_body(self, pb: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        r_bc = quat_to_rotmat(np.asarray(self.world.q_bc))
        return self.camera.visible(pb @ r_bc)

    def _drawn_panels(self, cam: FloatArray) -> list[tuple[int, float]]:
        """(index, distance) of the panels drawn from camera centre ``cam``: in range, not
        edge-on, not so close that the camera is inside them."""
        out = []
        for k, p in enumerate(self.panels):
            d = cam - p.center
            dist = float(np.linalg.norm(d))
            if dist > self.world.scenario.max_range_m or dist < 0.3:
                continue
            if abs(float(p.normal @ d)) / dist < self.settings.min_panel_cos:
                continue
            out.append((k, dist))
        return out

    def _draw_panels(self, img: NDArray[np.float32], x: float, y: float, yaw: float) -> None:
        cam = self._camera_center(x, y)
        r_bm = self._to_body(yaw)
        r_mb = r_bm.T.astype(np.float32)
        hh, ww = img.shape
        order = [(dist, k) for k, dist in self._drawn_panels(cam)]
        for dist, k in sorted(order, reverse=True):  # far first: near panels cover them
            p = self.panels[k]
            half = p.size / 2
            corners = np.array(
                [p.center + i * half * p.e1 + j * half * p.e2 for i in (-1, 1) for j in (-1, 1)]
                + [p.center]
            )
            pix, ok = self._project_body((corners - cam) @ r_bm.T)
            pix = pix[np.all(np.isfinite(pix), axis=1)]
            if pix.shape[0] < 5 or not ok.any():
                continue
            u0, v0 = np.floor(pix.min(axis=0)).astype(int) - 3
            u1, v1 = np.ceil(pix.max(axis=0)).astype(int) + 4
            u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, ww), min(v1, hh)
            if u1 <= u0 or v1 <= v0 or (u1 - u0) * (v1 - v0) > 400_000:
                continue
            rays = self.table.rays[v0:v1, u0:u1] @ r_mb.T  # map-frame directions
            n = p.normal.astype(np.float32)
            denom = rays @ n
            # a ray along the panel's plane (edge-on) has no hit: s infinite or NaN there,
            # and so its (a, b); ``ok_pix`` leaves those pixels out
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.float32(n @ (p.center - cam)) / denom
                hit = (cam.astype(np.float32) + rays * s[..., None]) - p.center.astype(np.float32)
                a = hit @ p.e1.astype(np.float32)
                b = hit @ p.e2.astype(np.float32)
            ok_pix = np.isfinite(s) & (s > 0)
            mip = self.panel_mip[k]
            texel_m = p.size / PANEL_TEXELS
            foot = dist * float(np.nanmedian(self.table.pixel_angle[v0:v1, u0:u1]))
            lv = int(np.clip(math.floor(math.log2(max(foot / texel_m, 1.0))), 0, len(mip) - 1))
            tex = mip[lv]
            # level-0 texel coordinates (row 0 at the top of the panel), then level lv's:
            # level-L texel k is centred on level-0 texel 2^L·k (cv2.pyrDown)
            k = np.float32(1.0 / 2**lv)
            mx = ((a / p.size + 0.5) * PANEL_TEXELS - 0.5).astype(np.float32) * k
            my = ((0.5 - b / p.size) * PANEL_TEXELS - 0.5).astype(np.float32) * k
            mx[~ok_pix] = -10.0
            my[~ok_pix] = -10.0
            val = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            with np.errstate(invalid="ignore"):
                cover = _panel_cover(a, b, p.size, foot / texel_m)
            cover[~(ok_pix & np.isfinite(cover))] = 0.0
            cover *= self.table.valid[v0:v1, u0:u1]
            roi = img[v0:v1, u0:u1]
            roi += cover * (val - roi)

    # ------------------------------------------------------------------------ ground truth

    def landmark_pixels(self, x: float, y: float, yaw: float) -> tuple[FloatArray, NDArray]:
        """Exact pixels of every landmark point and whether it is visible in this frame (in
        range, in the annulus, its panel not edge-on, not hidden behind a nearer panel)."""
        cam = self._camera_center(x, y)
        centers = np.array([p.center for p in self.panels]).reshape(-1, 3)
        d = cam - centers
        dist = np.linalg.norm(d, axis=1)
        normals = np.array([p.normal for p in self.panels]).reshape(-1, 3)
        facing = np.abs(np.einsum("ij,ij->i", normals, d)) / np.maximum(dist, 1e-9)
        pix, ok = self._project_body((centers - cam) @ self._to_body(yaw).T)
        ok &= (dist <= self.world.scenario.max_range_m) & (facing >= self.settings.min_panel_cos)
        if ok.any():  # hidden behind a nearer panel: not visible
            seen = self.true_points(x, y, yaw, pix[ok])
            ok[ok] = np.linalg.norm(seen - centers[ok], axis=1) < 0.02
        return pix, ok

    def true_points(self, x: float, y: float, yaw: float, pixels: FloatArray) -> FloatArray:
        """The map-frame 3-D point each pixel sees (NaN for the sky): the nearest of the
        drawn panels and the ground along the pixel's ray (truth for tracks)."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        out = np.full((pixels.shape[0], 3), np.nan)
        ok = self.camera.valid(pixels)
        if not ok.any():
            return out
        r_bc = quat_to_rotmat(np.asarray(self.world.q_bc))
        rays = (self.camera.lift(pixels[ok]) @ r_bc.T) @ self._to_body(yaw)  # map frame
        cam = self._camera_center(x, y)
        pix_angle = float(np.median(self.table.pixel_angle[self.table.valid]))
        best = np.full(rays.shape[0], np.inf)
        pts = np.full((rays.shape[0], 3), np.nan)
        down = rays[:, 2] < -1e-9
        s_ground = np.where(down, -cam[2] / np.where(down, rays[:, 2], -1.0), np.inf)
        s_ground[s_ground > GROUND_MAX_RANGE_M * 2] = np.inf
        hit = np.isfinite(s_ground)
        best[hit] = s_ground[hit]
        pts[hit] = cam + rays[hit] * s_ground[hit, None]
        for k, _ in self._drawn_panels(cam):
            p = self.panels[k]
            denom = rays @ p.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (p.normal @ (p.center - cam)) / denom
            x3 = cam + rays * s[:, None] - p.center
            a, b = x3 @ p.e1, x3 @ p.e2
            # a corner on the panel's outline is seen up to ~1.5 px outside it (blur):
            # it belongs to the panel, not to what lies behind it
            tol = TRUTH_TOLERANCE_PX * pix_angle * np.abs(s)
            half = p.size / 2
            inside = (s > 0) & (np.abs(a) <= half + tol) & (np.abs(b) <= half + tol)
            closer = inside & (s < best)
            a, b = np.clip(a, -half, half), np.clip(b, -half, half)
            on_panel = p.center + a[:, None] * p.e1 + b[:, None] * p.e2
            best[closer] = s[closer]
            pts[closer] = on_panel[closer]
        out[ok] = pts
        return out
