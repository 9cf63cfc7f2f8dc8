"""The Occ3D-nuScenes class table: ids, names, colours.

Ids 0..16 follow nuScenes-lidarseg's 16+1 challenge classes (0 = others), 17 = free.
Colours are the palette Occ3D / SurroundOcc / the AGO paper use in their figures (RGB).
"""

from __future__ import annotations

import numpy as np

OCC3D_CLASSES: tuple[str, ...] = (
    "others",                # 0
    "barrier",               # 1
    "bicycle",               # 2
    "bus",                   # 3
    "car",                   # 4
    "construction_vehicle",  # 5
    "motorcycle",            # 6
    "pedestrian",            # 7
    "traffic_cone",          # 8
    "trailer",               # 9
    "truck",                 # 10
    "driveable_surface",     # 11
    "other_flat",            # 12
    "sidewalk",              # 13
    "terrain",               # 14
    "manmade",               # 15
    "vegetation",            # 16
    "free",                  # 17
)
FREE = 17
IGNORE = 255
# Training only, never written to a file: a pseudo-label voxel the LiDAR hit but no 2-D mask labelled
# ("occupied, class unknown"): the occupancy loss counts it occupied, the grounding loss ignores it.
OCCUPIED_UNLABELLED = 254
NUM_SEMANTIC = 17  # classes 0..16
OCC3D_ID = {name: i for i, name in enumerate(OCC3D_CLASSES)}

# RGB colours, one per id 0..17 (free is drawn light grey where it is drawn at all).
OCC3D_COLORS = np.array(
    [
        [0, 0, 0],         # others
        [255, 120, 50],    # barrier
        [255, 192, 203],   # bicycle
        [255, 255, 0],     # bus
        [0, 150, 245],     # car
        [0, 255, 255],     # construction_vehicle
        [200, 180, 0],     # motorcycle
        [255, 0, 0],       # pedestrian
        [255, 240, 150],   # traffic_cone
        [135, 60, 0],      # trailer
        [160, 32, 240],    # truck
        [255, 0, 255],     # driveable_surface
        [139, 137, 137],   # other_flat
        [75, 0, 75],       # sidewalk
        [150, 240, 80],    # terrain
        [230, 230, 250],   # manmade
        [0, 175, 0],       # vegetation
        [240, 240, 240],   # free
    ],
    dtype=np.uint8,
)

# Classes the paper's mIoU* leaves out (no reliable prompt for them).
MIOU_STAR_EXCLUDED = ("others", "other_flat")


def class_color(name_or_id: str | int) -> np.ndarray:
    i = OCC3D_ID[name_or_id] if isinstance(name_or_id, str) else int(name_or_id)
    return OCC3D_COLORS[i]
