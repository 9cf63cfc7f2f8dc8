"""Camera rendering by ray casting the world: RGB image, per-pixel Occ3D class and depth.

`render_camera(world, prims, camera, ego2global, rng, noise_std)` takes a `Camera` (ego frame
calibration), the ego pose and the frame's primitives (world frame) and gives
  rgb (H, W, 3) uint8, semantic (H, W) uint8 Occ3D id (255 = sky / nothing),
  depth (H, W) float32 metres along the optical axis (camera z; 0 = nothing),
  ids (H, W) int32 first-hit primitive (raycast.GROUND / SKY), any_hits (N,) rays intersecting each primitive.
Pixel (col, row) is the ray through (col + 0.5, row + 0.5). Appearance: per-class procedural
albedo (noise, lane markings, paving tiles, windows, leaf noise, stripes...) times Lambertian
shading from the scene's sun, distance haze, a sky gradient with clouds, a slight blur and
Gaussian pixel noise.
"""

from __future__ import annotations

import cv2
import numpy as np

from ago_runtime.geometry.camera import Camera

from . import builder as B
from .agents import CLOTH_COLORS
from .world import World
from .raycast import MAP_CLASS, SKY, PrimitiveSet, cast, local_points, surface_normals

_NOISE = {}


def noise_tables() -> tuple[np.ndarray, np.ndarray]:
    """Two fixed 256x256 tileable noise textures in [0, 1]: fine (pixel-scale) and smooth (blobs)."""
    if not _NOISE:
        rng = np.random.default_rng(12345)
        raw = np.tile(rng.random((256, 256)).astype(np.float32), (3, 3))
        fine = cv2.GaussianBlur(raw, (0, 0), 0.8)[256:512, 256:512]
        big = rng.random((16, 16)).astype(np.float32)
        big = cv2.resize(np.tile(big, (3, 3)), (768, 768), interpolation=cv2.INTER_CUBIC)[256:512, 256:512]
        for name, a in (("fine", fine), ("big", big)):
            a = (a - a.min()) / (a.max() - a.min() + 1e-9)
            _NOISE[name] = a.astype(np.float32)
    return _NOISE["fine"], _NOISE["big"]


def _lookup(table: np.ndarray, u: np.ndarray, v: np.ndarray, scale: float) -> np.ndarray:
    return table[(np.floor(v * scale).astype(np.int64) & 255), (np.floor(u * scale).astype(np.int64) & 255)]


SURFACE_COLORS = np.array([
    [0.33, 0.33, 0.34],  # road
    [0.38, 0.37, 0.37],  # parking
    [0.62, 0.60, 0.57],  # sidewalk
    [0.28, 0.44, 0.17],  # grass
    [0.45, 0.36, 0.25],  # soil
    [0.70, 0.70, 0.67],  # island
    [0.18, 0.30, 0.38],  # water
    [0.42, 0.39, 0.35],  # rail bed
    [0.70, 0.65, 0.58],  # plaza
    [0.55, 0.52, 0.47],  # gravel
], np.float32)


def albedo_and_class(world: World, prims: PrimitiveSet, ids: np.ndarray, points: np.ndarray):
    """For hit points (m,3) on ids (m,) (primitive index or GROUND): albedo (m,3), class (m,), normal (m,3),
    and a surface code (m,) (255 for non-ground materials) used for LiDAR reflectivity."""
    fine, big = noise_tables()
    m = len(ids)
    albedo = np.zeros((m, 3), np.float32)
    normal = np.zeros((m, 3), np.float64)
    normal[:, 2] = 1.0
    cls = np.zeros(m, np.uint8)
    code = np.full(m, 255, np.uint8)
    is_prim = ids >= 0
    pid = np.where(is_prim, ids, 0)
    q = np.zeros((m, 3))
    mat = np.full(m, B.M_GROUND, np.uint8)
    if is_prim.any():
        q[is_prim] = local_points(prims, pid[is_prim], points[is_prim])
        normal[is_prim] = surface_normals(prims, pid[is_prim], q[is_prim])
        mat[is_prim] = prims.material[pid[is_prim]]
        cls[is_prim] = prims.cls[pid[is_prim]]
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    nf = _lookup(fine, x + 0.37 * z, y - 0.61 * z, 9.0)
    nb = _lookup(big, x + 0.2 * z, y + 0.3 * z, 0.35)
    # ---- ground-like (plane, slabs with raster class) ----
    g = (~is_prim) | (is_prim & (cls == MAP_CLASS))
    gi = np.nonzero(g)[0]
    if len(gi):
        gx, gy = x[gi], y[gi]
        sc, mk = world.raster_at(gx, gy)
        cls[gi] = B.SURFACE_CLASS[sc]
        nfg, nbg = nf[gi], nb[gi]
        col = SURFACE_COLORS[sc] * ((0.82 + 0.3 * nfg) * (0.88 + 0.24 * nbg))[:, None]

        def where(cond):
            return np.nonzero(cond)[0]

        k = where(sc == B.S_GRASS)
        col[k] = np.where(nbg[k, None] > 0.5, np.float32([0.36, 0.5, 0.2]), np.float32([0.24, 0.4, 0.15])) \
            * (0.7 + 0.6 * nfg[k, None])
        k = where((sc == B.S_SIDEWALK) | (sc == B.S_PLAZA))
        size = np.where(sc[k] == B.S_PLAZA, 1.2, 0.6)
        col[k[(np.mod(gx[k], size) < 0.04) | (np.mod(gy[k], size) < 0.04)]] *= 0.72
        k = where(sc == B.S_RAIL)
        col[k[(np.mod(gx[k], 0.65) < 0.22) | (np.mod(gy[k], 0.65) < 0.22)]] = [0.3, 0.22, 0.16]
        k = where(sc == B.S_WATER)
        col[k] = SURFACE_COLORS[B.S_WATER] * (0.9 + 0.2 * nbg[k, None]) + 0.1 * world.sky_horizon.astype(np.float32)
        painted = (mk > 0) & (sc <= B.S_PARKING)
        k = where(painted & (mk == 1))
        col[k] = np.float32([0.85, 0.85, 0.83]) * (0.9 + 0.1 * nfg[k, None])
        col[where(painted & (mk == 2))] = [0.85, 0.68, 0.2]
        code[gi] = np.where(painted, 250, sc)  # 250 = painted marking (bright for the LiDAR)
        k = where(is_prim[gi] & (np.abs(normal[gi, 2]) < 0.5))  # curb faces
        col[k] = np.float32([0.72, 0.72, 0.7]) * (0.85 + 0.2 * nfg[k, None])
        albedo[gi] = col
    # ---- primitives with their own material: each material computed on its own pixels only ----
    p_idx = np.nonzero(is_prim & ~g)[0]
    if len(p_idx):
        mt_all = mat[p_idx]
        for m_id in np.unique(mt_all):
            ix = p_idx[mt_all == m_id]
            albedo[ix] = _material(world, prims, int(m_id), pid[ix], q[ix], normal[ix], nf[ix, None], nb[ix, None],
                                   x[ix], y[ix], z[ix])
            code[ix] = 200 + m_id
    return np.clip(albedo, 0, 1), cls, normal, code


def _material(world, prims, mt, i, qq, normal, f, bg, x, y, z):
    """Albedo (k,3) of k hit points on primitives i (all of material mt); qq local points, f/bg noise (k,1)."""
    fine, big = noise_tables()
    base = prims.color[i].astype(np.float32)
    h = prims.half[i]
    n_loc = _local_normal(prims, i, normal)
    along = np.where(np.abs(n_loc[:, 0]) > np.abs(n_loc[:, 1]), qq[:, 1], qq[:, 0])
    zb = qq[:, 2] + h[:, 2]  # height above the primitive's base
    vertical = np.abs(normal[:, 2]) < 0.5
    if mt == B.M_BUILDING:
        sp = np.maximum(prims.param[i], 1e-3)
        brick = base[:, 0] > base[:, 2] * 1.4
        c = base * (0.85 + 0.25 * f)
        mortar = brick & (np.mod(zb, 0.3) < 0.04)
        c[mortar] = c[mortar] * 0.6 + 0.3
        floor_h = sp + 0.7
        fa = np.mod(along, sp) / sp
        fz = np.mod(zb, floor_h) / floor_h
        win = (prims.param[i] > 0) & vertical & (zb > 1.2) & (fa > 0.25) & (fa < 0.78) & (fz > 0.32) & (fz < 0.82)
        glass = np.array([0.14, 0.18, 0.24]) + 0.2 * bg * world.sky_horizon[None]
        c[win] = glass[win]
        roof = ~vertical
        c[roof] = np.array([0.32, 0.31, 0.3]) * (0.8 + 0.3 * f[roof])
        return c
    if mt == B.M_WALL:
        return base * (0.75 + 0.35 * f) * np.where(np.mod(along, 2.5) < 0.06, 0.7, 1.0)[:, None]
    if mt == B.M_BODY:
        c = base * (0.93 + 0.1 * f)
        c[zb < 0.08] *= 0.4
        lamp = vertical & (np.abs(n_loc[:, 0]) > 0.9) & (np.abs(qq[:, 1]) > h[:, 1] - 0.35) & (zb > h[:, 2] * 1.2)
        c[lamp] = np.where(n_loc[lamp, :1] > 0, [0.95, 0.95, 0.85], [0.8, 0.1, 0.08])
        return c
    if mt == B.M_CABIN:
        half_along = np.where(np.abs(n_loc[:, 0]) > np.abs(n_loc[:, 1]), h[:, 1], h[:, 0])
        pillar = np.abs(along) > half_along - 0.1
        glassc = np.array([0.1, 0.12, 0.15]) + 0.25 * bg * world.sky_horizon[None]
        return np.where((vertical & ~pillar)[:, None], glassc, base * 0.95)
    if mt == B.M_TIRE:
        return np.array([0.07, 0.07, 0.07]) * (0.7 + 0.6 * f)
    if mt == B.M_FOLIAGE:
        leaf = _lookup(fine, x * 1.7 + z, y * 1.7 - z * 1.3, 14.0)[:, None]
        return base * (0.45 + 0.9 * leaf) * (0.8 + 0.4 * bg)
    if mt == B.M_BARK:
        return base * (0.6 + 0.6 * _lookup(fine, along * 8, zb * 0.5, 6.0)[:, None])
    if mt == B.M_PERSON:
        trousers = CLOTH_COLORS[prims.param[i].astype(np.int64) % len(CLOTH_COLORS)]
        legs = zb < h[:, 2] * 2 * 0.48
        return np.where(legs[:, None], trousers, base) * (0.85 + 0.2 * f)
    if mt == B.M_SIGN:
        face = np.abs(n_loc[:, 0]) > 0.9
        symbol = face & (np.abs(qq[:, 1]) < 0.1) & (np.abs(qq[:, 2]) < 0.22)
        c = np.where(face[:, None], base, [0.5, 0.5, 0.52])
        c[symbol] = [0.95, 0.95, 0.95]
        return c
    if mt == B.M_TLIGHT:
        lamp_z = (0.3, 0.0, -0.3)
        c = np.full((len(i), 3), 0.1, np.float32)
        front = np.abs(n_loc[:, 0]) > 0.9
        for k, lc in enumerate(([0.9, 0.1, 0.1], [0.95, 0.7, 0.1], [0.1, 0.85, 0.3])):
            disk = front & (qq[:, 1] ** 2 + (qq[:, 2] - lamp_z[k]) ** 2 < 0.1 ** 2)
            lit = prims.param[i] == k
            c[disk] = np.where(lit[disk, None], lc, np.array(lc) * 0.25)
        return c
    if mt == B.M_CONE:
        band = (zb > h[:, 2] * 0.8) & (zb < h[:, 2] * 1.2)
        return np.where(band[:, None], [0.95, 0.95, 0.95], base)
    if mt == B.M_BARRIER:
        stripe = np.mod(along + zb, 0.6) < 0.3
        return np.where(stripe[:, None], [0.95, 0.95, 0.95], base)
    if mt == B.M_CONCRETE:
        return base * (0.75 + 0.35 * f)
    if mt == B.M_PLASTIC:
        ribs = (prims.param[i] > 0) & vertical & (np.mod(along, 0.45) < 0.06)
        c = base * (0.9 + 0.15 * f)
        c[ribs] *= 0.7
        return c
    if mt == B.M_BUS:
        band = vertical & (zb > 1.0) & (zb < h[:, 2] * 2 - 0.35)
        pillar = np.mod(along, 1.4) < 0.12
        glassc = np.array([0.12, 0.14, 0.18]) + 0.25 * bg * world.sky_horizon[None]
        return np.where((band & ~pillar)[:, None], glassc, base * (0.93 + 0.1 * f))
    return base * (0.9 + 0.2 * f)  # metal, skin, anything else


def _local_normal(prims, ids, n):
    c, s = np.cos(prims.yaw[ids]), np.sin(prims.yaw[ids])
    return np.stack([c * n[:, 0] + s * n[:, 1], -s * n[:, 0] + c * n[:, 1], n[:, 2]], axis=1)


class CameraRays:
    """Unit ray directions of every pixel in the camera frame and their z component (depth = t * z)."""

    def __init__(self, camera: Camera):
        H, W_ = camera.height, camera.width
        u, v = np.meshgrid(np.arange(W_) + 0.5, np.arange(H) + 0.5)
        pix = np.stack([u, v, np.ones_like(u)], axis=-1)
        d = pix @ np.linalg.inv(camera.intrinsics).T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        self.dirs_cam = d.astype(np.float32)
        self.zfactor = d[..., 2].astype(np.float32)


def camera_rects(cam2world: np.ndarray, K: np.ndarray, width: int, height: int, lo: np.ndarray, hi: np.ndarray,
                 near: float = 0.05) -> list[tuple[int, int, int, int, int]]:
    """Pixel rectangles (index, row0, row1, col0, col1) covering each AABB's projection (near-plane clipped)."""
    if len(lo) == 0:
        return []
    world2cam = np.linalg.inv(cam2world)
    sel = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], bool)
    corners = np.where(sel[None], hi[:, None, :], lo[:, None, :])                  # (N, 8, 3)
    pc = corners @ world2cam[:3, :3].T + world2cam[:3, 3]
    edges = np.array([(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])
    pa, pb = pc[:, edges[:, 0]], pc[:, edges[:, 1]]                               # (N, 12, 3)
    za, zb = pa[..., 2], pb[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = (near - za) / (zb - za)
    crossing = ((za - near) * (zb - near) < 0)
    pe = pa + np.where(crossing, tt, 0)[..., None] * (pb - pa)
    pts = np.concatenate([pc, pe], axis=1)                                          # (N, 20, 3)
    valid = np.concatenate([pc[..., 2] >= near, crossing], axis=1)
    zz = np.where(valid, pts[..., 2], 1.0)
    u = K[0, 0] * pts[..., 0] / zz + K[0, 2]
    v = K[1, 1] * pts[..., 1] / zz + K[1, 2]
    umin = np.where(valid, u, np.inf).min(1)
    umax = np.where(valid, u, -np.inf).max(1)
    vmin = np.where(valid, v, np.inf).min(1)
    vmax = np.where(valid, v, -np.inf).max(1)
    keep = valid.any(1) & (umax >= 0) & (umin < width) & (vmax >= 0) & (vmin < height)
    idx = np.nonzero(keep)[0]
    c0 = np.clip(np.floor(umin[idx]) - 1, 0, width).astype(int)
    c1 = np.clip(np.ceil(umax[idx]) + 1, 0, width).astype(int)
    r0 = np.clip(np.floor(vmin[idx]) - 1, 0, height).astype(int)
    r1 = np.clip(np.ceil(vmax[idx]) + 1, 0, height).astype(int)
    ok = (c1 > c0) & (r1 > r0)
    return list(zip(idx[ok].tolist(), r0[ok].tolist(), r1[ok].tolist(), c0[ok].tolist(), c1[ok].tolist()))


def render_camera(world: World, prims: PrimitiveSet, aabb: tuple[np.ndarray, np.ndarray], camera: Camera,
                  rays: CameraRays, ego2global: np.ndarray, rng: np.random.Generator, noise_std: float = 3.0,
                  exposure: float = 1.0):
    cam2world = ego2global @ camera.cam2ego
    origin = cam2world[:3, 3]
    dirs = rays.dirs_cam @ cam2world[:3, :3].T.astype(np.float32)                                    # (H, W, 3) world
    rects = camera_rects(cam2world, camera.intrinsics, camera.width, camera.height, *aabb)
    t, ids, any_hits = cast(origin, dirs, prims, rects, max_distance=2000.0)
    H, W_ = t.shape
    hit = ids != SKY
    flat_ids = ids[hit]
    pts = origin + t[hit][:, None] * dirs[hit]
    albedo, cls, normal, _ = albedo_and_class(world, prims, flat_ids, pts)
    ambient = 0.42 + 0.18 * normal[:, 2]
    diffuse = 0.62 * np.clip(normal @ world.sun, 0, None)
    col = albedo * (ambient + diffuse)[:, None]
    haze = (1 - np.exp(-t[hit] / 450.0))[:, None]
    col = col * (1 - haze) + world.sky_horizon[None] * haze
    img = np.zeros((H, W_, 3), np.float32)
    img[hit] = col
    # sky gradient + clouds
    sky = ~hit
    if sky.any():
        d = dirs[sky]
        e = np.clip(d[:, 2], 0, 1)
        g = np.clip(e * 2.5, 0, 1)[:, None] ** 0.7
        sc = world.sky_horizon[None] * (1 - g) + world.sky_top[None] * g
        fine, big = noise_tables()
        dz = np.maximum(d[:, 2], 0.03)
        cloud = _lookup(big, d[:, 0] / dz * 3.0, d[:, 1] / dz * 3.0, 0.5)[:, None]
        cloud = np.clip((cloud - 0.55) * 2.5, 0, 1) * np.clip(d[:, 2] * 8, 0, 1)[:, None]
        img[sky] = sc * (1 - 0.8 * cloud) + 0.95 * cloud
    img = cv2.GaussianBlur(img * exposure, (3, 3), 0.6)
    img = img * 255.0 + noise_std * rng.standard_normal(img.shape, dtype=np.float32)
    rgb = np.clip(img, 0, 255).astype(np.uint8)
    semantic = np.full((H, W_), 255, np.uint8)
    semantic[hit] = cls
    depth = np.where(hit, t * rays.zfactor, 0.0).astype(np.float32)
    return rgb, semantic, depth, ids, any_hits
