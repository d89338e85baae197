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
            raise ValueError(f"min_coverage must be in [0, 1), got {self.min_coverage}")


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
    p = (np.asarray(points, dtype=np.float64) - np.asarray(pose.location)) @ pose.matrix()
    depth = -p[:, 2]
    f = pose.focal_px(width)
    safe = np.where(depth > 1e-9, depth, 1e-9)
    x = 0.5 * width + f * p[:, 0] / safe
    y = 0.5 * height - f * p[:, 1] / safe
    return np.stack([x, y], axis=1), depth


def view_ok(points: np.ndarray, pose: CameraPose, width: int, height: int, ranges: CameraRanges) -> bool:
    """The whole car in frame (with a margin), in front of the camera, covering enough."""
    xy, depth = project(points, pose, width, height)
    if np.any(depth < 0.1):
        return False
    m = ranges.margin * width
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    if lo[0] < m or lo[1] < m or hi[0] > width - m or hi[1] > height - m:
        return False
    return (hi[0] - lo[0]) * (hi[1] - lo[1]) >= ranges.min_coverage * width * height


def sample_camera(rng: np.random.Generator, points: np.ndarray, width: int, height: int,
                  ranges: CameraRanges = CameraRanges()) -> CameraPose:
    """Draw poses until one keeps the car (given by sample `points`) whole and large enough.

    The camera is also kept out of the car's bounding box (plus 0.3 m).
    """
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
        pose = CameraPose(
            location=tuple(float(v) for v in loc), rotation=tuple(tuple(float(v) for v in row) for row in look_at(loc, target)),
            target=tuple(float(v) for v in target), focal_length=float(focal), sensor_width=ranges.sensor_width,
        )
        if view_ok(points, pose, width, height, ranges):
            return pose
    raise CameraError(
        f"no valid camera in {ranges.max_tries} draws: the car never fits the frame with radius "
        f"{ranges.radius_min}..{ranges.radius_max} m and focal {ranges.focal_min}..{ranges.focal_max} mm; "
        "widen the ranges or lower --min-coverage"
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
