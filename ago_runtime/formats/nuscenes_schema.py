"""Fixed parts of the nuScenes schema shared by the reader and the writer, and pose <-> record helpers.

- quaternions are nuScenes' [w, x, y, z] (Hamilton, rotation of the child frame into the parent);
- a pose record {"translation": [x, y, z], "rotation": [w, x, y, z]} is the 4x4 child2parent matrix
  (ego_pose: ego2global; calibrated_sensor: sensor2ego), metres;
- `CATEGORIES`: the 32 nuScenes(-lidarseg) category names in their lidarseg `index` order;
- `ATTRIBUTES`, `VISIBILITY_LEVELS`: nuScenes' attribute names and the 4 visibility bins.
"""

from __future__ import annotations

import math

import numpy as np

from ago_runtime.errors import AgoInputError

TABLE_NAMES: tuple[str, ...] = (
    "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map",
    "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility",
)

LIDAR_CHANNEL = "LIDAR_TOP"

# nuScenes-lidarseg category.json order: record `index` = position in this tuple.
CATEGORIES: tuple[tuple[str, str], ...] = (
    ("noise", "Points with no clear meaning (lidarseg only)."),
    ("animal", "An animal."),
    ("human.pedestrian.adult", "An adult pedestrian."),
    ("human.pedestrian.child", "A child pedestrian."),
    ("human.pedestrian.construction_worker", "A person at work on a construction site."),
    ("human.pedestrian.personal_mobility", "A person on a scooter, skateboard or segway."),
    ("human.pedestrian.police_officer", "A police officer."),
    ("human.pedestrian.stroller", "A stroller (pushed by a person)."),
    ("human.pedestrian.wheelchair", "A wheelchair."),
    ("movable_object.barrier", "A temporary road barrier."),
    ("movable_object.debris", "Debris on the road."),
    ("movable_object.pushable_pullable", "A trolley, bin or similar object pushed or pulled by a person."),
    ("movable_object.trafficcone", "A traffic cone."),
    ("static_object.bicycle_rack", "A rack of parked bicycles."),
    ("vehicle.bicycle", "A bicycle."),
    ("vehicle.bus.bendy", "An articulated bus."),
    ("vehicle.bus.rigid", "A rigid bus."),
    ("vehicle.car", "A car, van or SUV."),
    ("vehicle.construction", "A construction vehicle."),
    ("vehicle.emergency.ambulance", "An ambulance."),
    ("vehicle.emergency.police", "A police vehicle."),
    ("vehicle.motorcycle", "A motorcycle or scooter."),
    ("vehicle.trailer", "A trailer."),
    ("vehicle.truck", "A truck."),
    ("flat.driveable_surface", "Road surface a car may drive on."),
    ("flat.other", "Other flat ground (traffic islands, rail tracks...)."),
    ("flat.sidewalk", "A sidewalk."),
    ("flat.terrain", "Grass, soil, sand."),
    ("static.manmade", "Buildings, walls, poles, signs."),
    ("static.other", "Other static background."),
    ("static.vegetation", "Trees, bushes."),
    ("vehicle.ego", "The ego vehicle itself."),
)
CATEGORY_NAMES: tuple[str, ...] = tuple(name for name, _ in CATEGORIES)

ATTRIBUTES: tuple[tuple[str, str], ...] = (
    ("vehicle.moving", "The vehicle is moving."),
    ("vehicle.stopped", "The vehicle is stopped with a driver, e.g. at a light."),
    ("vehicle.parked", "The vehicle is parked."),
    ("cycle.with_rider", "Someone rides the bicycle or motorcycle."),
    ("cycle.without_rider", "Nobody rides the bicycle or motorcycle."),
    ("pedestrian.sitting_lying_down", "The person sits or lies down."),
    ("pedestrian.standing", "The person stands."),
    ("pedestrian.moving", "The person walks or runs."),
)

# visibility token -> (level, description); the token is the string "1".."4" as in nuScenes.
VISIBILITY_LEVELS: dict[str, tuple[str, str]] = {
    "1": ("v0-40", "visibility of whole object is between 0 and 40%"),
    "2": ("v40-60", "visibility of whole object is between 40 and 60%"),
    "3": ("v60-80", "visibility of whole object is between 60 and 80%"),
    "4": ("v80-100", "visibility of whole object is between 80 and 100%"),
}


def quaternion_to_matrix(q) -> np.ndarray:
    """[w, x, y, z] (any norm > 0) -> (3, 3) rotation matrix, float64."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> unit quaternion [w, x, y, z] with w >= 0 (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def yaw_to_quaternion(yaw: float) -> np.ndarray:
    """Rotation by `yaw` radians about +z -> [w, x, y, z]."""
    return np.array([np.cos(yaw / 2.0), 0.0, 0.0, np.sin(yaw / 2.0)])


def record_to_matrix(record: dict) -> np.ndarray:
    """A record with "translation" and "rotation" ([w, x, y, z]) -> (4, 4) float64 child2parent."""
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(record["rotation"])
    m[:3, 3] = np.asarray(record["translation"], dtype=np.float64)
    return m


def matrix_to_record(m: np.ndarray) -> dict:
    """(4, 4) rigid transform -> {"translation": [3 floats], "rotation": [w, x, y, z]} (plain floats)."""
    m = np.asarray(m, dtype=np.float64)
    return {"translation": [float(v) for v in m[:3, 3]],
            "rotation": [float(v) for v in matrix_to_quaternion(m[:3, :3])]}


def check_rigid(m: np.ndarray, tol: float = 1e-4) -> str | None:
    """None when `m` is a finite 4x4 rigid transform (rotation + translation), else what is wrong."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        return "contains NaN or inf"
    if np.abs(m[:3, 3]).max() > MAX_POSE_METRES:
        return f"its translation is beyond {MAX_POSE_METRES:g} m"
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=tol) or np.linalg.det(r) < 0:
        return "its 3x3 part is not a rotation"
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        return "its last row is not [0, 0, 0, 1]"
    return None


# ---------------------------------------------------------------------------- record checks
MAX_POSE_METRES = 1e7       # |translation| of a pose record (global coordinates: a city is ~1e4 m)
# table -> {field: kind}: the fields the reader uses, checked when a table is read (kinds below)
TABLE_FIELDS: dict[str, dict[str, str]] = {
    "sensor": {"channel": "str"},
    "calibrated_sensor": {"sensor_token": "str", "translation": "vec3", "rotation": "quat",
                          "camera_intrinsic": "intrinsic"},
    "ego_pose": {"translation": "vec3", "rotation": "quat", "timestamp": "int?"},
    "scene": {"name": "str"},
    "sample": {"scene_token": "str", "timestamp": "int"},
    "sample_data": {"sample_token": "str", "calibrated_sensor_token": "str", "ego_pose_token": "str",
                    "filename": "str", "timestamp": "int", "is_key_frame": "bool?", "prev": "str?"},
}


def _finite_numbers(value, n: int) -> bool:
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value))


def _field_problem(kind: str, value) -> str | None:
    optional = kind.endswith("?")
    kind = kind.rstrip("?")
    if value is None or (optional and value == ""):
        return None if optional else "is missing"
    if kind == "str":
        return None if isinstance(value, str) else f"must be a string, got {type(value).__name__}"
    if kind == "int":
        return None if isinstance(value, int) and not isinstance(value, bool) else \
            f"must be an integer, got {type(value).__name__}"
    if kind == "bool":
        return None if isinstance(value, bool) else f"must be true or false, got {type(value).__name__}"
    if kind == "vec3":
        if not _finite_numbers(value, 3):
            return "must be 3 finite numbers"
        return None if max(abs(v) for v in value) <= MAX_POSE_METRES else f"is beyond {MAX_POSE_METRES:g} m"
    if kind == "quat":
        if not _finite_numbers(value, 4) or not 1e-6 < math.sqrt(sum(v * v for v in value)) < 1e6:
            return "must be 4 finite numbers of a non-zero norm ([w, x, y, z])"
        return None
    if kind == "intrinsic":   # [] for a LiDAR or radar, else 3x3
        if value == []:
            return None
        ok = isinstance(value, list) and len(value) == 3 and all(_finite_numbers(row, 3) for row in value)
        return None if ok else "must be [] or a 3x3 matrix of finite numbers"
    raise ValueError(kind)


def check_table(name: str, records: list, path) -> None:
    """Refuse (AgoInputError naming `path`) a record of table `name` whose fields the reader uses have the
    wrong type or an absurd value (TABLE_FIELDS): the first such record is named, by token and field."""
    fields = TABLE_FIELDS.get(name, {})
    for rec in records:
        for field, kind in fields.items():
            problem = _field_problem(kind, rec.get(field))
            if problem:
                raise AgoInputError(path, f"record {str(rec.get('token'))[:40]!r}: {field} {problem}")
