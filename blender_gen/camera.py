"""Camera sampling (the paper's rule: within 8 m horizontally, at most 3 m high).

Pure NumPy pinhole maths so that the constraints can be checked over thousands of draws
without Blender. Conventions follow Blender: the camera looks down its local -Z with +Y
up; `rotation` holds the camera's right, up and back axes as columns (world space).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np


class CameraError(ValueError):
    """The camera ranges admit no view that keeps the car in frame."""


@dataclass(frozen=True)
class CameraRanges:
    """Where cameras may go. Defaults: the paper's 8 m radius and 3 m height."""

    radius_min: float = 3.5
    radius_max: float = 8.0
    height_min: float = 0.3
    height_max: float = 3.0
    focal_min: float = 24.0  # mm, on a 36 mm wide sensor
    focal_max: float = 60.0
    sensor_width: float = 36.0
    target_jitter: float = 0.25  # m, std-dev of the look-at point around the car's centre
    min_coverage: float = 0.08  # the car's 2-D bounding box must cover this fraction of the frame
    # At most this fraction. Below 1 the camera distance is solved for a coverage drawn uniformly in
    # [min_coverage, max_coverage] (photo-like framing); at 1 the distance is drawn (the paper's rule).
    max_coverage: float = 1.0
    margin: float = 0.02  # the car keeps this fraction of the width away from the borders
    max_tries: int = 500

    def validate(self) -> None:
        if not 0 <= self.radius_min < self.radius_max:
            raise ValueError(f"camera radius range must satisfy 0 <= min < max, got {self.radius_min}..{self.radius_max}")
        if not self.height_min < self.height_max:
            raise ValueError(f"camera height range must satisfy min < max, got {self.height_min}..{self.height_max}")
        if not 0 < self.focal_min <= self.focal_max:
            raise ValueError(f"focal length range must satisfy 0 < min <= max, got {self.focal_min}..{self.focal_max}")
        if not 0 <= self.min_coverage < 1:
            raise ValueError(f"--min-coverage {self.min_coverage}: expected a fraction of the frame in [0, 1)")
        if not self.min_coverage < self.max_coverage <= 1:
            raise ValueError(f"--max-coverage {self.max_coverage}: expected above --min-coverage "
                             f"({self.min_coverage}) and at most 1")


@dataclass(frozen=True)
class CameraPose:
    location: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...]  # 3x3, columns = right, up, back
    target: tuple[float, float, float]
    focal_length: float  # mm
    sensor_width: float  # mm, horizontal sensor fit

    def matrix(self) -> np.ndarray:
        return np.asarray(self.rotation, dtype=np.float64)

    def focal_px(self, width: int) -> float:
        return self.focal_length / self.sensor_width * width

    def to_json(self) -> dict:
        d = asdict(self)
        d["rotation_euler_xyz_deg"] = [round(float(a), 6) for a in euler_xyz_deg(self.matrix())]
        d["sensor_fit"] = "HORIZONTAL"
        return d


def look_at(location: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera rotation (columns right, up, back) looking from `location` at `target`, no roll."""
    fwd = np.asarray(target, dtype=np.float64) - np.asarray(location, dtype=np.float64)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return np.stack([right, up, -fwd], axis=1)


def euler_xyz_deg(m: np.ndarray) -> np.ndarray:
    """Blender's XYZ Euler angles (R = Rz @ Ry @ Rx) of a rotation matrix, in degrees."""
    sy = -m[2, 0]
    y = np.arcsin(np.clip(sy, -1.0, 1.0))
    if abs(sy) < 1 - 1e-9:
        x = np.arctan2(m[2, 1], m[2, 2])
        z = np.arctan2(m[1, 0], m[0, 0])
    else:  # gimbal lock
        x = np.arctan2(-m[1, 2], m[1, 1])
        z = 0.0
    return np.rad2deg([x, y, z])


def project(points: np.ndarray, pose: CameraPose, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (x right, y down, origin top-left) and depth along the view axis."""
    return _project(points, np.asarray(pose.location), pose.matrix(), pose.focal_px(width), width, height)


def _project(points: np.ndarray, location: np.ndarray, rotation: np.ndarray, focal_px: float, width: int,
             height: int) -> tuple[np.ndarray, np.ndarray]:
    """`project` from a camera's parts, without building a CameraPose (the framed sampler's bisection)."""
    p = (np.asarray(points, dtype=np.float64) - location) @ rotation
    depth = -p[:, 2]
    safe = np.where(depth > 1e-9, depth, 1e-9)
    x = 0.5 * width + focal_px * p[:, 0] / safe
    y = 0.5 * height - focal_px * p[:, 1] / safe
    return np.stack([x, y], axis=1), depth


def _whole_in_frame(xy: np.ndarray, depth: np.ndarray, width: int, height: int, ranges: CameraRanges) -> bool:
    """In front of the camera and inside the frame, `ranges.margin` of the width from its borders."""
    if np.any(depth < 0.1):
        return False
    m = ranges.margin * width
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return not (lo[0] < m or lo[1] < m or hi[0] > width - m or hi[1] > height - m)


def _box_fraction(xy: np.ndarray, width: int, height: int) -> float:
    """The fraction of the frame the points' 2-D bounding box covers (above 1 when it overflows)."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return float((hi[0] - lo[0]) * (hi[1] - lo[1]) / (width * height))


def coverage(points: np.ndarray, pose: CameraPose, width: int, height: int) -> float:
    """The fraction of the frame the car's 2-D bounding box covers (unclipped: above 1 when it
    overflows the frame)."""
    return _box_fraction(project(points, pose, width, height)[0], width, height)


def view_ok(points: np.ndarray, pose: CameraPose, width: int, height: int, ranges: CameraRanges) -> bool:
    """The whole car in frame (with a margin), in front of the camera, covering enough (and, with
    a maximum below 1, not too much)."""
    xy, depth = project(points, pose, width, height)
    if not _whole_in_frame(xy, depth, width, height, ranges):
        return False
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    area = (hi[0] - lo[0]) * (hi[1] - lo[1])  # in pixels, as sets made before compared it: the same draws
    return ranges.min_coverage * width * height <= area and (
        ranges.max_coverage >= 1 or area <= ranges.max_coverage * width * height)


def _pose(loc: np.ndarray, target: np.ndarray, focal: float, ranges: CameraRanges) -> CameraPose:
    return CameraPose(
        location=tuple(float(v) for v in loc), rotation=tuple(tuple(float(v) for v in row) for row in look_at(loc, target)),
        target=tuple(float(v) for v in target), focal_length=float(focal), sensor_width=ranges.sensor_width,
    )


def sample_camera(rng: np.random.Generator, points: np.ndarray, width: int, height: int,
                  ranges: CameraRanges = CameraRanges()) -> CameraPose:
    """Draw poses until one keeps the car (given by sample `points`) whole and large enough.

    The camera is also kept out of the car's bounding box (plus 0.3 m). With `max_coverage` below 1
    the framing is drawn instead of the distance (`_sample_framed`).
    """
    if ranges.max_coverage < 1:
        return _sample_framed(rng, points, width, height, ranges)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    for _ in range(ranges.max_tries):
        r = np.sqrt(rng.uniform(ranges.radius_min**2, ranges.radius_max**2))  # uniform over the annulus
        a = rng.uniform(0.0, 2.0 * np.pi)
        loc = np.array([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), rng.uniform(ranges.height_min, ranges.height_max)])
        target = centre + rng.normal(0.0, ranges.target_jitter, 3)
        focal = rng.uniform(ranges.focal_min, ranges.focal_max)
        if np.all(loc > lo - 0.3) and np.all(loc < hi + 0.3):
            continue
        pose = _pose(loc, target, focal, ranges)
        if view_ok(points, pose, width, height, ranges):
            return pose
    raise _no_camera(ranges)


_HULLS: dict[bytes, np.ndarray] = {}  # a car's convex hull per point set (a model is reused for several views)


def _hull(points: np.ndarray) -> np.ndarray:
    """The points of the convex hull: they project to the same bounding box as all the points."""
    import hashlib

    key = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=16).digest()
    if key not in _HULLS:
        from scipy.spatial import ConvexHull, QhullError

        try:
            _HULLS.clear()
            _HULLS[key] = points[ConvexHull(points).vertices]
        except (QhullError, ValueError):  # flat or tiny point sets
            _HULLS[key] = points
    return _HULLS[key]


def _sample_framed(rng: np.random.Generator, points: np.ndarray, width: int, height: int,
                   ranges: CameraRanges) -> CameraPose:
    """A pose whose car covers a drawn fraction of the frame. Direction, height, look-at point and
    focal length are drawn as in `sample_camera`; then, along that direction, the coverages the
    radius range reaches with the car whole in the frame are found (coverage falls with distance),
    a coverage is drawn uniformly in their overlap with [min_coverage, max_coverage] and the
    distance is bisected for it. A direction with no overlap is drawn again."""
    hull = _hull(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    for _ in range(ranges.max_tries):
        a = rng.uniform(0.0, 2.0 * np.pi)
        z = rng.uniform(ranges.height_min, ranges.height_max)
        target = centre + rng.normal(0.0, ranges.target_jitter, 3)
        focal = rng.uniform(ranges.focal_min, ranges.focal_max)
        direction = np.array([np.cos(a), np.sin(a)])
        f = focal / ranges.sensor_width * width

        def box(r: float) -> tuple[bool, float]:
            """(the car whole in the frame with the margin, its coverage) from distance r."""
            loc = np.array([*(centre[:2] + r * direction), z])
            xy, depth = _project(hull, loc, look_at(loc, target), f, width, height)
            return _whole_in_frame(xy, depth, width, height, ranges), _box_fraction(xy, width, height)

        def bisect(near: float, far: float, too_close, steps: int) -> float:
            for _step in range(steps):
                mid = 0.5 * (near + far)
                near, far = (mid, far) if too_close(mid) else (near, mid)
            return far

        fits_far, c_far = box(ranges.radius_max)
        if not fits_far:
            continue  # the car does not fit even from the farthest point
        closest = ranges.radius_min
        if not box(closest)[0]:  # the car fits from farther away only: 8 m / 2^16, about 0.1 mm
            closest = bisect(closest, ranges.radius_max, lambda r: not box(r)[0], 16)
        c_lo, c_hi = max(ranges.min_coverage, c_far), min(ranges.max_coverage, box(closest)[1])
        if c_lo > c_hi:
            continue
        want = rng.uniform(c_lo, c_hi)
        r = bisect(closest, ranges.radius_max, lambda r: box(r)[1] > want, 20)
        pose = _pose(np.array([*(centre[:2] + r * direction), z]), target, focal, ranges)
        loc = np.array(pose.location)
        if np.all(loc > lo - 0.3) and np.all(loc < hi + 0.3):
            continue
        if view_ok(points, pose, width, height, ranges):
            return pose
    raise _no_camera(ranges)


def _no_camera(ranges: CameraRanges) -> CameraError:
    cover = (f"coverage {ranges.min_coverage}..{ranges.max_coverage}" if ranges.max_coverage < 1
             else f"coverage at least {ranges.min_coverage}")
    return CameraError(
        f"no valid camera in {ranges.max_tries} draws: the car never fits the frame with radius "
        f"{ranges.radius_min}..{ranges.radius_max} m, focal {ranges.focal_min}..{ranges.focal_max} mm and {cover}; "
        "widen the ranges or lower --min-coverage / --max-coverage"
    )


@dataclass(frozen=True)
class Orbit:
    """A camera path around one car (`iae-gen turntable`): frame k of n sits at angle
    start + 360 k / n degrees, `radius` m from the car's centre and `height` m above the ground,
    looking at the centre, with one focal length (Blender's defaults: no roll, fixed seed).
    `focal` None: the longest focal length (whole mm, 10..80) at which every frame shows the whole car."""

    frames: int
    radius: float = 6.0
    height: float = 1.6
    focal: float | None = None  # mm, 36 mm wide sensor; None = fit the car
    start_deg: float = 0.0
    paint: str | None = None  # None: drawn once from the seed
    env_rotation_deg: float | None = None  # None: drawn once from the seed


def orbit_focal(points: np.ndarray, orbit: Orbit, width: int, height: int,
                ranges: CameraRanges = CameraRanges()) -> float:
    """The orbit's focal length: its own, or the longest that keeps the car whole in every frame."""
    if orbit.focal is not None:
        return float(orbit.focal)

    def fits(focal: int) -> bool:
        trial = replace(orbit, focal=float(focal))
        return all(_orbit_view(points, trial, k, width, height, ranges)[1] for k in range(orbit.frames))

    # a shorter lens only widens the view from the same place, so "fits" is monotone in the focal
    # length: bisect the whole millimetres 10..80 (7 checks of every frame instead of up to 71)
    if fits(10):
        lo, hi = 10, 81  # fits(lo), and nothing at hi or above is tried
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if fits(mid) else (lo, mid)
        return float(lo)
    raise CameraError(f"turntable: the car does not fit the {width}x{height} frame at --radius {orbit.radius} m, "
                      f"--height {orbit.height} m even with a 10 mm lens; increase --radius")


def _orbit_view(points: np.ndarray, orbit: Orbit, frame: int, width: int, height: int,
                ranges: CameraRanges) -> tuple[CameraPose, bool]:
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    a = np.deg2rad(orbit.start_deg + 360.0 * frame / orbit.frames)
    loc = np.array([centre[0] + orbit.radius * np.cos(a), centre[1] + orbit.radius * np.sin(a), orbit.height])
    pose = CameraPose(location=tuple(float(v) for v in loc),
                      rotation=tuple(tuple(float(v) for v in row) for row in look_at(loc, centre)),
                      target=tuple(float(v) for v in centre), focal_length=float(orbit.focal),
                      sensor_width=ranges.sensor_width)
    return pose, view_ok(points, pose, width, height, replace(ranges, min_coverage=0.0))


def orbit_pose(points: np.ndarray, orbit: Orbit, frame: int, width: int, height: int,
               ranges: CameraRanges = CameraRanges()) -> CameraPose:
    """Camera of one frame of an orbit (with a set focal length); a frame that cannot show the
    whole car is an error."""
    pose, ok = _orbit_view(points, orbit, frame, width, height, ranges)
    if not ok:
        raise CameraError(f"turntable frame {frame}: the car does not fit the {width}x{height} frame at "
                          f"--radius {orbit.radius} m, --height {orbit.height} m with --focal {orbit.focal} mm; "
                          "increase --radius or lower --focal")
    return pose
