"""Occ3D-Waymo labels of the synthetic world (`ago synth --rig waymo|front`).

The world is built in Occ3D-nuScenes classes plus a material per primitive; `waymo_label_of` turns
(class, material) into an Occ3D-Waymo id (`ago_runtime.classes.OCC3D_WAYMO`): signs, traffic lights
and poles are the manmade primitives of those materials, tree trunks the bark of trees, bicyclists the
person riding a bicycle. Where Waymo has no such class the choice is ours: barrier and others ->
general_object, terrain -> walkable, other_flat -> road, a person on a motorcycle -> motorcycle.
`waymo_pixel_labels` gives the same ids per rendered pixel (the Occ3D-Waymo layout's synthetic/semantic
maps); `fov_mask` is Occ3D-Waymo's `infov`.
"""

from __future__ import annotations

import numpy as np

from ago_runtime.classes import OCC3D_ID as C
from ago_runtime.classes import OCC3D_WAYMO
from ago_runtime.geometry.grid import Grid

from .builder import M_BARK, M_METAL, M_PERSON, M_SIGN, M_SKIN, M_TLIGHT

# ---- Occ3D-nuScenes class (+ material) -> Occ3D-Waymo id ---------------------------------------------
W = {n: OCC3D_WAYMO.id_of(n) for n in OCC3D_WAYMO.names}
NUSCENES_TO_WAYMO = np.full(256, W["general_object"], np.uint8)   # any class not listed: general object
for _ns, _w in (("car", "vehicle"), ("truck", "vehicle"), ("bus", "vehicle"), ("trailer", "vehicle"),
                ("construction_vehicle", "vehicle"), ("pedestrian", "pedestrian"), ("bicycle", "bicycle"),
                ("motorcycle", "motorcycle"), ("traffic_cone", "construction_cone"), ("barrier", "general_object"),
                ("others", "general_object"), ("driveable_surface", "road"), ("other_flat", "road"),
                ("sidewalk", "walkable"), ("terrain", "walkable"), ("manmade", "building"),
                ("vegetation", "vegetation")):
    NUSCENES_TO_WAYMO[C[_ns]] = W[_w]
NUSCENES_TO_WAYMO[C["free"]] = OCC3D_WAYMO.free_id


def waymo_label_of(cls: np.ndarray, material: np.ndarray) -> np.ndarray:
    """(N,) uint8 Occ3D-Waymo ids of primitives given their Occ3D-nuScenes class and material."""
    cls = np.asarray(cls, np.uint8)
    material = np.asarray(material)
    out = NUSCENES_TO_WAYMO[cls].copy()
    manmade = cls == C["manmade"]
    out[manmade & (material == M_SIGN)] = W["sign"]
    out[manmade & (material == M_TLIGHT)] = W["traffic_light"]
    out[manmade & (material == M_METAL)] = W["pole"]          # street-light, sign and traffic-light poles
    out[(cls == C["vegetation"]) & (material == M_BARK)] = W["tree_trunk"]
    rider = np.isin(material, (M_PERSON, M_SKIN))
    out[(cls == C["bicycle"]) & rider] = W["bicyclist"]      # the person on a bicycle
    return out


def waymo_pixel_labels(semantic: np.ndarray, primitive: np.ndarray, material: np.ndarray) -> np.ndarray:
    """A rendered (H, W) map of Occ3D-nuScenes ids (255 = sky) and the (H, W) primitive index of each pixel
    (negative: ground or sky; `material` indexes by it) -> (H, W) uint8 Occ3D-Waymo ids, 255 kept: the rule
    the ground truth's voxels follow (`waymo_label_of`), so a pixel and the voxel it shows agree."""
    semantic = np.asarray(semantic, np.uint8)
    mat = np.full(semantic.shape, -1, np.int64)
    hit = primitive >= 0
    mat[hit] = np.asarray(material)[primitive[hit]]
    out = waymo_label_of(semantic.ravel(), mat.ravel()).reshape(semantic.shape)
    return np.where(semantic == 255, np.uint8(255), out).astype(np.uint8)


def fov_mask(grid: Grid, cameras) -> np.ndarray:
    """(X, Y, Z) uint8: voxels whose centre projects into some camera's image, in front of it (no occlusion test):
    Occ3D-Waymo's `infov`."""
    centres = grid.centres().reshape(-1, 3)
    inside = np.zeros(len(centres), bool)
    for cam in cameras:
        inside |= cam.project(centres)[2]
    return inside.reshape(grid.shape).astype(np.uint8)
