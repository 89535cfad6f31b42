"""Built-in synthetic data: a small deterministic ray-cast scene with a simulated LiDAR and MDE.

The package cannot ship real data, so the demo and the unit tests use this generator. It is
SIMULATED data, stated as such in every frame's ``notes``:

* The scene is a handful of analytic primitives (infinite planes and boxes that may be turned
  about the vertical axis) ray-cast with numpy (vectorised ray-plane and ray-box slab
  intersection; no mesh library needed). ``kind="street"`` is a KITTI-like road with buildings,
  parked cars, poles and an open sky (no depth there); ``kind="room"`` is a closed room with a
  table, a cabinet and boxes.
* ``depth_gt`` is the exact z-depth at every pixel centre (0 where a ray hits nothing, e.g. the
  sky, or hits beyond ``max_depth``).
* ``rgb`` is rendered with per-object colours, Lambert shading and procedural textures (world-
  anchored value noise, lane markings, windows, floor boards) so that images are not flat and
  colours stay consistent from frame to frame.
* ``lidar`` simulates a 64-beam spinning LiDAR (HDL-64E elevation pattern, +2 to -24.9 deg, one
  return per beam and azimuth step): every beam is cast against the scene, its hit converted to
  a camera-frame point and projected with `gpdepth3d.project_points` (closest point per pixel).
  The beam pattern decides *which* pixels carry a measurement (scan lines, nothing in the sky or
  beyond range, gaps between beams). With ``LidarModel.snap_to_pixel_centres=True`` (the
  default) the value of a measured pixel is the scene depth along that pixel's centre ray plus
  the LiDAR noise, so that, without noise, LiDAR and ``depth_gt`` agree exactly. With ``False``
  the value is the raw return's z-depth, which differs from the pixel-centre depth by the depth
  change across up to half a pixel (as in a real projected scan).
* ``mde`` simulates a monocular depth network (it is NOT a network output): ground truth (the sky
  filled with ``max_depth``) blurred with a Gaussian, multiplied by a global scale error and by
  ``exp`` of a smooth low-frequency random field, plus white multiplicative noise. With the
  default `MDESimulation` its relative RMS error against ``depth_gt`` is about 10 to 30 % (tested),
  most of it the global scale error, which a scale alignment removes.

Conventions follow `gpdepth3d.camera`: OpenCV camera frame, z-depth in metres, poses
``T_world_camera``. The world frame is z-up: x east, y north (the street runs along +y), z up.
The LiDAR frame is the Velodyne one (x forward, y left, z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator, Literal

import numpy as np

from ..camera import PinholeCamera
from ..depthmap import fill_nearest
from ..errors import InvalidInputError, ShapeError, describe
from ..measurements import SparseDepth, project_points

SceneKind = Literal["street", "room"]

_EPS = 1e-6

# HDL-64E: upper block 32 lasers from +2.0 to -8.33 deg, lower block 32 from -8.83 to -24.33 deg
# (nominal vertical field of view +2 to -24.9 deg).
HDL64_ELEVATIONS_DEG: tuple[float, ...] = tuple(
    float(x) for x in np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.87, -24.87, 32)])
)


# ---------------------------------------------------------------------- options
@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR.

    Attributes:
        elevations_deg: Elevation of each beam in the LiDAR frame, degrees (default: HDL-64E).
        azimuth_step_deg: Horizontal angle between two firings, degrees (HDL-64E at 10 Hz: 0.08).
        min_range: Returns closer than this (metres) are dropped.
        noise: Standard deviation of the depth noise, metres (0 = noise-free).
        offset: (3,) position of the LiDAR origin in the camera frame, metres (KITTI's is about
            (0, -0.08, -0.27)); 0 puts it at the camera centre, so it sees exactly what the camera sees.
        snap_to_pixel_centres: Measured value of a pixel = scene depth along the pixel-centre ray
            (+ noise) instead of the raw return's z-depth; see the module docstring.
    """

    elevations_deg: tuple[float, ...] = HDL64_ELEVATIONS_DEG
    azimuth_step_deg: float = 0.08
    min_range: float = 0.5
    noise: float = 0.02
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    snap_to_pixel_centres: bool = True

    def __post_init__(self) -> None:
        el = tuple(float(x) for x in self.elevations_deg)
        if len(el) == 0 or not all(math.isfinite(x) and -90.0 < x < 90.0 for x in el):
            raise InvalidInputError("elevations_deg", "one or more beam elevations in (-90, 90) degrees", el)
        object.__setattr__(self, "elevations_deg", el)
        if not (math.isfinite(self.azimuth_step_deg) and 0.0 < self.azimuth_step_deg <= 10.0):
            raise InvalidInputError("azimuth_step_deg", "a step in (0, 10] degrees", self.azimuth_step_deg)
        if not (math.isfinite(self.min_range) and self.min_range >= 0):
            raise InvalidInputError("min_range", "a finite range >= 0 (metres)", self.min_range)
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise InvalidInputError("noise", "a finite standard deviation >= 0 (metres)", self.noise)
        off = tuple(float(x) for x in self.offset)
        if len(off) != 3 or not all(math.isfinite(x) for x in off):
            raise InvalidInputError("offset", "three finite coordinates (metres)", self.offset)
        object.__setattr__(self, "offset", off)

    @classmethod
    def hdl64(cls, **overrides) -> "LidarModel":
        """Velodyne HDL-64E (KITTI's sensor): 64 beams from +2 to -24.9 deg, 0.08 deg azimuth step."""
        return cls(**overrides)

    @classmethod
    def vlp16(cls, **overrides) -> "LidarModel":
        """Velodyne VLP-16: 16 beams from -15 to +15 deg every 2 deg, 0.2 deg azimuth step (sparser)."""
        base = dict(elevations_deg=tuple(float(x) for x in np.arange(-15.0, 15.1, 2.0)), azimuth_step_deg=0.2)
        base.update(overrides)
        return cls(**base)


@dataclass(frozen=True)
class MDESimulation:
    """How the simulated monocular depth deviates from the ground truth.

    ``mde = scale * blur(gt) * exp(field) * (1 + noise * N(0, 1))`` with ``field`` a smooth
    zero-mean Gaussian random field of standard deviation ``field_amplitude``.

    Attributes:
        scale: Global scale error (1 = metric).
        blur_sigma: Gaussian blur standard deviation as a fraction of the image width.
        field_amplitude: Standard deviation of the low-frequency log-depth error.
        field_lengthscale: Correlation length of that error as a fraction of the image width.
        noise: Standard deviation of the white relative noise per pixel.
    """

    scale: float = 1.15
    blur_sigma: float = 0.006
    field_amplitude: float = 0.08
    field_lengthscale: float = 0.25
    noise: float = 0.01

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise InvalidInputError("scale", "a finite scale > 0", self.scale)
        for name in ("blur_sigma", "field_amplitude", "noise"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(name, "a finite value >= 0", value)
        if not (math.isfinite(self.field_lengthscale) and self.field_lengthscale > 0):
            raise InvalidInputError("field_lengthscale", "a finite fraction of the width > 0", self.field_lengthscale)


@dataclass(frozen=True)
class SyntheticFrame:
    """One simulated frame (see the module docstring: every field here is SIMULATED).

    Attributes:
        rgb: (H, W, 3) uint8 rendered colour image.
        depth_gt: (H, W) float64 exact z-depth, metres; 0 = no surface (sky) or beyond max_depth.
        camera: Intrinsics and image size.
        T_world_camera: (4, 4) camera pose in the z-up world frame.
        lidar: Simulated 64-beam LiDAR measurements on the image grid (closest point per pixel).
        mde: (H, W) float64 simulated monocular depth, metres (> 0 everywhere).
        notes: Human-readable statement that the data is simulated and how.
        lidar_points: (N, 3) raw LiDAR returns in the LiDAR frame (x forward, y left, z up),
            metres, noise included (see `scan_lidar` for which beams are cast).
        T_camera_lidar: (4, 4) transform from the LiDAR frame to the camera frame.
        kind: "street" or "room".
        seed: The seed the scene was made from.
        index: Frame index within a `sequence` (0 for `make_scene`).
        max_depth: Depth cut-off of ``depth_gt`` and ``lidar``, metres.
    """

    rgb: np.ndarray
    depth_gt: np.ndarray
    camera: PinholeCamera
    T_world_camera: np.ndarray
    lidar: SparseDepth
    mde: np.ndarray
    notes: str
    lidar_points: np.ndarray
    T_camera_lidar: np.ndarray
    kind: str
    seed: int
    index: int = 0
    max_depth: float = field(default=80.0)

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return self.camera.K

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return self.camera.shape


# ---------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class _Plane:
    point: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit
    colour: tuple[float, float, float]
    pattern: str

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        denom = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.point - o) @ self.normal) / denom
        t = np.where(np.isfinite(t) & (t > _EPS), t, np.inf)
        sign = -np.sign(denom)
        sign = np.where(sign == 0, 1.0, sign)
        return t, sign[:, None] * self.normal[None, :]


@dataclass(frozen=True)
class _Box:
    centre: np.ndarray  # (3,)
    half: np.ndarray  # (3,) half extents along the box axes
    yaw: float  # rotation about world z, radians
    colour: tuple[float, float, float]
    pattern: str

    @property
    def R(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slab test; from inside the box the exit face is hit (how the room walls work)."""
        R = self.R
        ol = (o - self.centre) @ R  # world -> box frame (R^T p for row vectors)
        dl = d @ R
        safe = np.where(np.abs(dl) < 1e-12, np.where(dl < 0, -1e-12, 1e-12), dl)
        inv = 1.0 / safe
        t1 = (-self.half - ol) * inv
        t2 = (self.half - ol) * inv
        tmin = np.minimum(t1, t2)
        tmax = np.maximum(t1, t2)
        t_near = tmin.max(axis=1)
        t_far = tmax.min(axis=1)
        hit = t_far >= np.maximum(t_near, _EPS)
        from_outside = t_near > _EPS
        t = np.where(hit, np.where(from_outside, t_near, t_far), np.inf)
        axis = np.where(from_outside, tmin.argmax(axis=1), tmax.argmin(axis=1))
        n_local = np.zeros_like(dl)
        rows = np.arange(dl.shape[0])
        n_local[rows, axis] = -np.sign(safe[rows, axis])  # faces the ray origin
        return t, n_local @ R.T


@dataclass(frozen=True)
class SyntheticScene:
    """A static scene of planes and boxes that can be rendered and scanned.

    Build one with `build_scene`; `make_scene` and `sequence` do so for you.

    Attributes:
        kind: "street" or "room".
        seed: Seed of the layout and the textures.
        primitives: The planes and boxes.
        max_depth: Depth cut-off (metres).
        sky: True when rays may escape (the street's sky).
    """

    kind: str
    seed: int
    primitives: tuple
    max_depth: float
    sky: bool

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Casts rays against every primitive, nearest hit wins.

        Args:
            origins: (3,) or (N, 3) ray origins in the world frame, metres.
            directions: (N, 3) ray directions (need not be unit length).

        Returns:
            t: (N,) ray parameter of the hit (distance in units of the direction's length),
                inf where nothing is hit.
            index: (N,) index of the primitive hit, -1 where none.
            normal: (N, 3) unit surface normal at the hit, facing the ray origin (0 where none).
        """
        d = np.asarray(directions, dtype=np.float64)
        origins = np.asarray(origins, dtype=np.float64)
        o = np.broadcast_to(origins, d.shape)
        n = d.shape[0]
        best = np.full(n, np.inf)
        index = np.full(n, -1, dtype=np.int64)
        normal = np.zeros((n, 3))
        common_origin = origins.shape == (3,)
        if common_origin:
            d_unit = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        for i, prim in enumerate(self.primitives):
            rays = None
            if common_origin and isinstance(prim, _Box):
                # Bounding-sphere cull: only rays passing within the box's radius are slab-tested.
                oc = prim.centre - origins
                radius = float(np.linalg.norm(prim.half)) * (1 + 1e-9) + 1e-9
                if float(oc @ oc) > radius * radius:
                    along = d_unit @ oc
                    rays = np.nonzero((along > 0) & (float(oc @ oc) - along * along <= radius * radius))[0]
                    if rays.size == 0:
                        continue
            if rays is None:
                t, nrm = prim.intersect(o, d)
                closer = t < best
                best = np.where(closer, t, best)
                index[closer] = i
                normal[closer] = nrm[closer]
            else:
                t, nrm = prim.intersect(o[rays], d[rays])
                closer = t < best[rays]
                sel = rays[closer]
                best[sel] = t[closer]
                index[sel] = i
                normal[sel] = nrm[closer]
        return best, index, normal

    def render(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Renders (depth_gt (H, W) metres, rgb (H, W, 3) uint8) at the pixel centres."""
        u, v = camera.pixel_grid()
        depth, index, normal, points, dirs_world = self._cast_pixels(camera, T_world_camera, u.ravel(), v.ravel())
        rgb = self._shade(index, normal, points, dirs_world, depth)
        h, w = camera.shape
        return depth.reshape(h, w), rgb.reshape(h, w, 3)

    def depth_at(self, camera: PinholeCamera, T_world_camera: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Exact z-depth (metres, 0 = none) along the rays through arbitrary (N, 2) pixel positions."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return self._cast_pixels(camera, T_world_camera, uv[:, 0], uv[:, 1])[0]

    def _cast_pixels(self, camera, T_world_camera, u, v):
        T = np.asarray(T_world_camera, dtype=np.float64)
        dirs_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=1)
        dirs_world = dirs_cam @ T[:3, :3].T
        t, index, normal = self.cast(T[:3, 3], dirs_world)
        # The camera-frame z of the hit is t because the camera-frame direction has z = 1.
        valid = np.isfinite(t) & (t <= self.max_depth)
        depth = np.where(valid, t, 0.0)
        index = np.where(valid, index, -1)
        points = T[:3, 3] + np.where(valid, t, 0.0)[:, None] * dirs_world
        return depth, index, normal, points, dirs_world

    # ------------------------------------------------------------------ colour
    def _shade(self, index, normal, points, dirs_world, depth) -> np.ndarray:
        n = index.shape[0]
        rgb = np.zeros((n, 3))
        unit = dirs_world / np.linalg.norm(dirs_world, axis=1, keepdims=True)
        sky_colour = self._sky(unit)
        light = np.array([0.45, -0.35, 0.82]) if self.kind == "street" else np.array([0.25, -0.55, 0.80])
        light = light / np.linalg.norm(light)
        lambert = np.clip(normal @ light, 0.0, 1.0)
        # Soft fill light from the camera so that faces turned away from the sun are not black.
        fill = np.abs(np.sum(normal * unit, axis=1))
        shade = 0.35 + 0.5 * lambert + 0.15 * fill
        f_coarse, f_fine = (0.6, 4.0) if self.kind == "street" else (2.0, 15.0)
        coarse = _value_noise(points, f_coarse, self.seed + 11)
        fine = _value_noise(points, f_fine, self.seed + 23)
        tex = 0.85 + 0.2 * coarse + 0.1 * fine
        for i, prim in enumerate(self.primitives):
            m = index == i
            if not m.any():
                continue
            base = np.broadcast_to(np.asarray(prim.colour, dtype=np.float64), (int(m.sum()), 3)).copy()
            base = _pattern(prim, points[m], normal[m], base)
            rgb[m] = base * (shade[m] * tex[m])[:, None]
        hit = index >= 0
        if self.kind == "street":
            fog = 1.0 - np.exp(-np.where(hit, depth, 0.0) / 250.0)
            rgb[hit] = rgb[hit] * (1 - fog[hit, None]) + sky_colour[hit] * fog[hit, None]
        rgb[~hit] = sky_colour[~hit]
        return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)

    def _sky(self, unit: np.ndarray) -> np.ndarray:
        up = np.clip(unit[:, 2], 0.0, 1.0)[:, None]
        horizon = np.array([0.80, 0.86, 0.93])
        zenith = np.array([0.35, 0.55, 0.85])
        return horizon * (1 - up) + zenith * up


def _pattern(prim, p: np.ndarray, normal: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Object-specific procedural texture on the base colour (p, normal: (n, 3) world points, normals)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if prim.pattern == "road":
        side = np.abs(x) > 6.0  # pavement
        base[side] = np.array([0.62, 0.60, 0.56])
        lane = (np.abs(x) < 0.09) & (np.mod(y, 6.0) < 3.0)
        edge = np.abs(np.abs(x) - 5.6) < 0.08
        base[lane | edge] = np.array([0.92, 0.92, 0.88])
    elif prim.pattern == "building":
        # Windows on a regular facade grid; "along" is the horizontal coordinate within the face.
        along = np.where(np.abs(normal[:, 0]) > np.abs(normal[:, 1]), y, x)
        win = (np.mod(z, 3.0) > 1.0) & (np.mod(z, 3.0) < 2.2) & (np.mod(along, 2.6) > 0.8) & (z > 1.5)
        base[win] = base[win] * 0.35 + np.array([0.15, 0.2, 0.3])
    elif prim.pattern == "wood":
        boards = np.mod(np.floor(x / 0.18), 3.0)
        base = base * (0.85 + 0.08 * boards)[:, None]
    elif prim.pattern == "tiles":
        grid = np.mod(np.floor(x / 0.5) + np.floor(y / 0.5), 2.0) == 0
        base = base * np.where(grid, 1.0, 0.8)[:, None]
    elif prim.pattern == "car":
        top = prim.centre[2] + prim.half[2]
        glass = (z > prim.centre[2] + 0.3 * prim.half[2]) & (z < top - 0.06) & (np.abs(normal[:, 2]) < 0.5)
        base[glass] = np.array([0.15, 0.18, 0.22])
    return base


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points."""
    h = (
        ix.astype(np.uint64) * np.uint64(73856093)
        ^ iy.astype(np.uint64) * np.uint64(19349663)
        ^ iz.astype(np.uint64) * np.uint64(83492791)
        ^ np.uint64((seed * 2654435761) & 0xFFFFFFFF)
    )
    h ^= h >> np.uint64(13)
    h *= np.uint64(0x5BD1E995)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def _value_noise(points: np.ndarray, frequency: float, seed: int) -> np.ndarray:
    """Smooth world-anchored value noise in [0, 1) at (n, 3) points (trilinear lattice interpolation)."""
    q = np.asarray(points, dtype=np.float64) * frequency
    q = np.where(np.isfinite(q), q, 0.0)
    f = np.floor(q)
    r = q - f
    r = r * r * (3 - 2 * r)  # smoothstep
    i = f.astype(np.int64)
    out = np.zeros(q.shape[0])
    with np.errstate(over="ignore"):
        for dx in (0, 1):
            wx = r[:, 0] if dx else 1 - r[:, 0]
            for dy in (0, 1):
                wy = r[:, 1] if dy else 1 - r[:, 1]
                for dz in (0, 1):
                    wz = r[:, 2] if dz else 1 - r[:, 2]
                    out += wx * wy * wz * _hash01(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
    return out


# ---------------------------------------------------------------------- scene layouts
def build_scene(seed: int = 0, *, kind: SceneKind = "street") -> SyntheticScene:
    """Lays out a deterministic static scene of planes and boxes.

    Args:
        seed: Seed of the layout (object sizes, positions, colours) and the textures.
        kind: "street" (KITTI-like road, 80 m depth cut-off) or "room" (closed indoor room,
            10 m cut-off).
    """
    seed = _check_seed(seed)
    rng = np.random.default_rng([seed, 1 if kind == "street" else 2])
    if kind == "street":
        return _street(rng, seed)
    if kind == "room":
        return _room(rng, seed)
    raise InvalidInputError("kind", "'street' or 'room'", kind)


def _box(centre, size, colour, pattern, yaw=0.0) -> _Box:
    return _Box(np.asarray(centre, float), np.asarray(size, float) / 2.0, float(yaw), tuple(colour), pattern)


def _street(rng: np.random.Generator, seed: int) -> SyntheticScene:
    prims: list = [_Plane(np.zeros(3), np.array([0.0, 0.0, 1.0]), (0.33, 0.33, 0.35), "road")]
    end = float(rng.uniform(55.0, 70.0))
    for side in (-1.0, 1.0):
        y = -30.0
        while y < end:
            length = float(rng.uniform(8.0, 18.0))
            gap = float(rng.uniform(0.0, 6.0)) if rng.random() < 0.5 else 0.0
            depth = float(rng.uniform(8.0, 14.0))
            height = float(rng.uniform(6.0, 18.0))
            setback = float(rng.uniform(7.5, 10.0))
            colour = rng.uniform([0.45, 0.35, 0.3], [0.85, 0.75, 0.65])
            cx = side * (setback + depth / 2)
            prims.append(_box((cx, y + length / 2, height / 2), (depth, length, height), colour, "building"))
            y += length + gap
        # Parked cars along the kerb and poles on the pavement.
        y = float(rng.uniform(3.0, 8.0))
        while y < end - 8:
            if rng.random() < 0.7:
                colour = rng.uniform(0.1, 0.9, size=3)
                x = side * float(rng.uniform(3.6, 4.4))
                yaw = float(rng.normal(0.0, 0.04))
                prims.append(_box((x, y, 0.75), (1.8, 4.3, 1.5), colour, "car", yaw))
            y += float(rng.uniform(6.0, 11.0))
        for y in np.arange(float(rng.uniform(4.0, 10.0)), end - 5, float(rng.uniform(12.0, 18.0))):
            prims.append(_box((side * 6.6, y, 2.5), (0.25, 0.25, 5.0), (0.3, 0.3, 0.32), "plain"))
    # A car ahead in the other lane and a cross street closed by a building row.
    prims.append(_box((-1.8, float(rng.uniform(14.0, 25.0)), 0.75), (1.8, 4.3, 1.5), rng.uniform(0.2, 0.9, 3), "car"))
    prims.append(_box((0.0, end + 12.0, 9.0), (80.0, 10.0, 18.0), (0.7, 0.62, 0.55), "building"))
    return SyntheticScene("street", seed, tuple(prims), 80.0, True)


def _room(rng: np.random.Generator, seed: int) -> SyntheticScene:
    w, d, h = float(rng.uniform(4.5, 6.0)), float(rng.uniform(5.5, 7.0)), float(rng.uniform(2.5, 2.9))
    wall = rng.uniform([0.7, 0.65, 0.55], [0.9, 0.88, 0.8])
    prims: list = [
        _box((0.0, 0.0, h / 2), (w, d, h), wall, "plain"),  # seen from inside: walls and ceiling
        _Plane(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), (0.55, 0.38, 0.22), "wood"),
    ]
    # Table with a box on it, a cabinet against the far wall, a few boxes on the floor.
    tx, ty = float(rng.uniform(-0.8, 0.8)), float(rng.uniform(0.3, 1.2))
    prims.append(_box((tx, ty, 0.72), (1.4, 0.8, 0.06), (0.45, 0.3, 0.2), "wood", float(rng.uniform(-0.3, 0.3))))
    for sx in (-0.6, 0.6):
        for sy in (-0.3, 0.3):
            prims.append(_box((tx + sx, ty + sy, 0.35), (0.06, 0.06, 0.7), (0.3, 0.2, 0.15), "plain"))
    prims.append(_box((tx + 0.2, ty, 0.87), (0.3, 0.25, 0.24), rng.uniform(0.2, 0.9, 3), "plain"))
    prims.append(_box((float(rng.uniform(-1.5, 1.5)), d / 2 - 0.3, 0.9), (1.2, 0.6, 1.8), (0.35, 0.4, 0.5), "tiles"))
    for _ in range(3):
        size = rng.uniform(0.25, 0.6, 3)
        x = float(rng.uniform(-w / 2 + 0.5, w / 2 - 0.5))
        y = float(rng.uniform(-0.5, d / 2 - 1.0))
        prims.append(_box((x, y, size[2] / 2), size, rng.uniform(0.2, 0.9, 3), "plain", float(rng.uniform(-0.6, 0.6))))
    return SyntheticScene("room", seed, tuple(prims), 10.0, False)


# ---------------------------------------------------------------------- cameras and poses
def _default_size(kind: str, width: int | None, height: int | None) -> tuple[int, int]:
    dw, dh = (320, 96) if kind == "street" else (160, 120)
    w = dw if width is None else width
    h = dh if height is None else height
    for name, value in (("width", w), ("height", h)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 8:
            raise InvalidInputError(name, "an integer image size >= 8 (pixels)", value)
    return int(w), int(h)


def default_camera(kind: SceneKind = "street", *, width: int | None = None, height: int | None = None) -> PinholeCamera:
    """The camera of a synthetic frame: KITTI-like (street) or Kinect-like (room) field of view.

    Square pixels; the focal length scales with the width (street: fx = 0.581 width, the KITTI
    ratio; room: fx = 0.914 width, the Kinect ratio).
    """
    if kind not in ("street", "room"):
        raise InvalidInputError("kind", "'street' or 'room'", kind)
    w, h = _default_size(kind, width, height)
    if kind == "street":
        f = 0.581 * w
        return PinholeCamera(f, f, (w - 1) / 2.0, 0.46 * h, w, h)
    f = 0.914 * w
    return PinholeCamera(f, f, (w - 1) / 2.0, (h - 1) / 2.0, w, h)


def pose_from_position_yaw_pitch(position, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """T_world_camera of a camera at ``position`` (world, z-up) looking along +y turned by yaw/pitch.

    Yaw turns left (counter-clockwise seen from above), pitch up; degrees.
    """
    psi, theta = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = np.array([-math.sin(psi) * math.cos(theta), math.cos(psi) * math.cos(theta), math.sin(theta)])
    right = np.array([math.cos(psi), math.sin(psi), 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)  # columns: camera x, y, z in the world
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def _poses(kind: str, n: int, step: float | None) -> list[np.ndarray]:
    if kind == "street":
        step = 1.0 if step is None else step
        return [pose_from_position_yaw_pitch((1.8, i * step, 1.65)) for i in range(n)]
    step = 0.15 if step is None else step
    return [pose_from_position_yaw_pitch((-0.3 + i * step, -2.2, 1.4), 6.0 - 4.0 * i, -12.0) for i in range(n)]


# ---------------------------------------------------------------------- sensors
def _T_lidar_world_parts(T_world_camera: np.ndarray, offset: tuple[float, float, float]) -> np.ndarray:
    """T_world_lidar: level LiDAR (Velodyne axes) at the camera position + offset, the camera's yaw."""
    T = np.asarray(T_world_camera, dtype=np.float64)
    forward = T[:3, 2].copy()
    forward[2] = 0.0
    if np.linalg.norm(forward) < 1e-9:  # camera looking straight up/down: use its y axis
        forward = -T[:3, 1].copy()
        forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, forward)
    Tw = np.eye(4)
    Tw[:3, :3] = np.stack([forward, left, up], axis=1)
    Tw[:3, 3] = T[:3, 3] + T[:3, :3] @ np.asarray(offset, dtype=np.float64)
    return Tw


def scan_lidar(
    scene: SyntheticScene,
    camera: PinholeCamera,
    T_world_camera: np.ndarray,
    lidar: LidarModel,
    depth_gt: np.ndarray,
    rng: np.random.Generator,
) -> tuple[SparseDepth, np.ndarray, np.ndarray]:
    """Simulates one LiDAR sweep over the camera's horizontal sector and projects it.

    Returns:
        sparse: measurements on the camera grid (closest return per pixel).
        points_lidar: (N, 3) returns in the LiDAR frame, metres (noise included): the beams of
            the azimuth sector the image covers, restricted to the beams pointing into the image
            when the LiDAR sits at the camera centre (others cannot be seen there).
        T_camera_lidar: (4, 4).
    """
    T_wc = np.asarray(T_world_camera, dtype=np.float64)
    T_wl = _T_lidar_world_parts(T_wc, lidar.offset)
    T_cl = np.linalg.inv(T_wc) @ T_wl
    # Azimuth sector covering the image (+ 2 deg margin), on the sensor's fixed azimuth lattice.
    h, w = camera.shape
    bu = np.concatenate([np.arange(w), np.arange(w), np.zeros(h), np.full(h, w - 1)]).astype(float)
    bv = np.concatenate([np.zeros(w), np.full(w, h - 1), np.arange(h), np.arange(h)]).astype(float)
    border = np.stack([(bu - camera.cx) / camera.fx, (bv - camera.cy) / camera.fy, np.ones_like(bu)], 1)
    border_l = border @ T_cl[:3, :3]  # camera -> LiDAR directions (R^T d)
    az = np.degrees(np.arctan2(border_l[:, 1], border_l[:, 0]))
    half = min(180.0, float(np.max(np.abs(az))) + 2.0)
    k = np.arange(math.ceil(-half / lidar.azimuth_step_deg), math.floor(half / lidar.azimuth_step_deg) + 1)
    azimuth = np.radians(k * lidar.azimuth_step_deg)
    elevation = np.radians(np.asarray(lidar.elevations_deg))
    el, azg = np.meshgrid(elevation, azimuth, indexing="ij")
    dirs_l = np.stack([np.cos(el) * np.cos(azg), np.cos(el) * np.sin(azg), np.sin(el)], axis=-1).reshape(-1, 3)
    if not np.any(lidar.offset):
        # LiDAR at the camera centre: a return projects where its beam direction does, so beams
        # outside the image (1 px margin) cannot produce a measurement and are not cast.
        uv, z = camera.project(dirs_l @ T_cl[:3, :3].T)
        inside = (z > 0) & (uv[:, 0] >= -1.5) & (uv[:, 0] <= w + 0.5) & (uv[:, 1] >= -1.5) & (uv[:, 1] <= h + 0.5)
        dirs_l = dirs_l[inside]
    t, index, _ = scene.cast(T_wl[:3, 3], dirs_l @ T_wl[:3, :3].T)
    hit = np.isfinite(t) & (t >= lidar.min_range)
    rng_noise = rng.normal(0.0, 1.0, size=t.shape)
    r = t[hit] + (lidar.noise * rng_noise[hit] if lidar.noise > 0 and not lidar.snap_to_pixel_centres else 0.0)
    points_l = dirs_l[hit] * r[:, None]
    points_c = points_l @ T_cl[:3, :3].T + T_cl[:3, 3]
    # The z cut-off (max_depth) applies to the camera-frame depth like depth_gt's.
    points_c_in = points_c[points_c[:, 2] <= scene.max_depth]
    sparse = project_points(points_c_in, camera)
    if lidar.snap_to_pixel_centres and len(sparse):
        rows, cols = sparse.v.astype(np.int64), sparse.u.astype(np.int64)
        value = depth_gt[rows, cols]
        keep = value > 0
        noise = lidar.noise * rng.normal(0.0, 1.0, size=value.shape) if lidar.noise > 0 else 0.0
        value = np.maximum(value + noise, 1e-3)
        sparse = SparseDepth(sparse.u[keep], sparse.v[keep], np.broadcast_to(value, keep.shape)[keep], camera.shape)
    return sparse, points_l, T_cl


def simulate_mde(
    depth_gt: np.ndarray, sim: MDESimulation, rng: np.random.Generator, *, fill_depth: float | None = None
) -> np.ndarray:
    """Simulated monocular depth (metres, > 0 everywhere) from ground truth; see `MDESimulation`.

    The one MDE stand-in of the project (the synthetic scenes, the ``gt-degraded`` front-end of
    `gpdepth3d.evaluation.evaluation`, the ``standin`` of `gpdepth3d.pipelines.batch`, the
    benchmarks and examples): never a network, always labelled as simulated.

    Args:
        depth_gt: (H, W) depth, metres (0/NaN = none; e.g. ground truth or densifiable points).
        sim: The error model.
        rng: Generator of the error field, then of the white noise.
        fill_depth: Depth of the pixels without one (e.g. the sky's far limit); None = the
            nearest pixel with a depth (`gpdepth3d.depthmap.fill_nearest`).

    Raises:
        ShapeError: ``depth_gt`` is not 2-D.
        EmptyInputError: ``fill_depth`` is None and no pixel has a depth.
    """
    import cv2

    gt = np.asarray(depth_gt, dtype=np.float64)
    if gt.ndim != 2:
        raise ShapeError("depth_gt", "an (H, W) depth map in metres", describe(gt))
    h, w = gt.shape
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(gt) & (gt > 0)
    filled = fill_nearest(gt, valid) if fill_depth is None else np.where(valid, gt, fill_depth)
    sigma = sim.blur_sigma * w
    blurred = cv2.GaussianBlur(filled, (0, 0), sigmaX=sigma, sigmaY=sigma) if sigma > 0.05 else filled
    field = _smooth_field((h, w), sim.field_lengthscale * w, rng) * sim.field_amplitude
    noise = rng.normal(0.0, 1.0, size=(h, w)) * sim.noise
    return np.maximum(sim.scale * blurred * np.exp(field) * (1.0 + noise), 1e-3)


def _smooth_field(shape: tuple[int, int], lengthscale_px: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-variance smooth Gaussian field (white noise convolved with a Gaussian)."""
    import cv2

    h, w = shape
    # The field is smooth on the scale of lengthscale_px: draw it on a grid `step` times coarser
    # (cheap blur) and interpolate up.
    step = max(1, int(lengthscale_px // 4))
    pad = int(math.ceil(2 * lengthscale_px / step)) + 2
    hc, wc = -(-h // step) + 2 * pad, -(-w // step) + 2 * pad
    white = rng.normal(0.0, 1.0, size=(hc, wc))
    sigma = lengthscale_px / math.sqrt(2.0) / step
    coarse = cv2.GaussianBlur(white, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    fine = cv2.resize(coarse, (wc * step, hc * step), interpolation=cv2.INTER_CUBIC)
    f = fine[pad * step : pad * step + h, pad * step : pad * step + w]
    std = float(f.std())
    return (f - f.mean()) / std if std > 0 else f


# ---------------------------------------------------------------------- public entry points
def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInputError("seed", "an integer >= 0", seed)
    return int(seed)


def _notes(kind: str, seed: int, lidar: LidarModel, mde: MDESimulation, index: int) -> str:
    return (
        f"SIMULATED data (gpdepth3d.datasets.synthetic, kind={kind!r}, seed={seed}, frame {index}): a ray-cast scene "
        "of planes and boxes, not a real recording. depth_gt: exact pixel-centre z-depth (0 = sky / beyond "
        f"max_depth). lidar: simulated {len(lidar.elevations_deg)}-beam spinning LiDAR "
        f"(azimuth step {lidar.azimuth_step_deg} deg, noise {lidar.noise} m, "
        f"{'values at pixel centres' if lidar.snap_to_pixel_centres else 'raw return depths'}). "
        f"mde: SIMULATED monocular depth, not a network output: ground truth blurred "
        f"(sigma {mde.blur_sigma} x width), global scale error x{mde.scale}, smooth log-depth error field "
        f"(std {mde.field_amplitude}, length {mde.field_lengthscale} x width), white relative noise {mde.noise}."
    )


def _frame(
    scene: SyntheticScene,
    camera: PinholeCamera,
    T_world_camera: np.ndarray,
    lidar: LidarModel,
    mde: MDESimulation,
    index: int,
) -> SyntheticFrame:
    depth_gt, rgb = scene.render(camera, T_world_camera)
    rng = np.random.default_rng([scene.seed, index, 7])
    sparse, points_l, T_cl = scan_lidar(scene, camera, T_world_camera, lidar, depth_gt, rng)
    mde_depth = simulate_mde(depth_gt, mde, rng, fill_depth=scene.max_depth)
    for a in (rgb, depth_gt, mde_depth, points_l):
        a.setflags(write=False)
    return SyntheticFrame(
        rgb=rgb,
        depth_gt=depth_gt,
        camera=camera,
        T_world_camera=T_world_camera,
        lidar=sparse,
        mde=mde_depth,
        notes=_notes(scene.kind, scene.seed, lidar, mde, index),
        lidar_points=points_l,
        T_camera_lidar=T_cl,
        kind=scene.kind,
        seed=scene.seed,
        index=index,
        max_depth=scene.max_depth,
    )


def make_scene(
    seed: int = 0,
    *,
    kind: SceneKind = "street",
    width: int | None = None,
    height: int | None = None,
    lidar: LidarModel | None = None,
    mde: MDESimulation | None = None,
) -> SyntheticFrame:
    """One SIMULATED frame: rendered RGB, exact depth, simulated 64-beam LiDAR and simulated MDE.

    Deterministic: the same arguments give identical arrays.

    Args:
        seed: Seed of the scene layout, textures and sensor noise (integer >= 0).
        kind: "street" (default size 320x96, KITTI-like field of view, sky without depth) or
            "room" (default 160x120, Kinect-like field of view).
        width: Image width in pixels (>= 8); the focal length scales with it.
        height: Image height in pixels (>= 8).
        lidar: The LiDAR (default `LidarModel()`: HDL-64E pattern, 2 cm noise, at the camera centre).
        mde: How the monocular depth is simulated (default `MDESimulation()`).

    Returns:
        A `SyntheticFrame`; its ``notes`` say that and how it is simulated.
    """
    scene = build_scene(seed, kind=kind)
    camera = default_camera(kind, width=width, height=height)
    return _frame(scene, camera, _poses(kind, 1, None)[0], lidar or LidarModel(), mde or MDESimulation(), 0)


def sequence(
    seed: int = 0,
    *,
    kind: SceneKind = "street",
    n_frames: int = 5,
    step: float | None = None,
    width: int | None = None,
    height: int | None = None,
    lidar: LidarModel | None = None,
    mde: MDESimulation | None = None,
) -> Iterator[SyntheticFrame]:
    """Yields ``n_frames`` SIMULATED posed frames of one static scene (for fusion and tracking).

    The street camera drives along +y by ``step`` metres per frame (default 1 m); the room
    camera slides sideways by ``step`` metres (default 0.15 m) while turning 4 degrees right per
    frame. Frame 0 equals `make_scene` with the same arguments. Sensor noise differs per frame.

    Args:
        seed, kind, width, height, lidar, mde: As for `make_scene`.
        n_frames: Number of frames (>= 1).
        step: Camera motion per frame, metres.
    """
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise InvalidInputError("n_frames", "an integer >= 1", n_frames)
    if step is not None and not (isinstance(step, (int, float)) and math.isfinite(step)):
        raise InvalidInputError("step", "a finite distance in metres", step)
    scene = build_scene(seed, kind=kind)
    camera = default_camera(kind, width=width, height=height)
    lidar, mde = lidar or LidarModel(), mde or MDESimulation()
    for i, T in enumerate(_poses(kind, int(n_frames), step)):
        yield _frame(scene, camera, T, lidar, mde, i)


__all__ = [
    "HDL64_ELEVATIONS_DEG",
    "LidarModel",
    "MDESimulation",
    "SyntheticFrame",
    "SyntheticScene",
    "build_scene",
    "default_camera",
    "make_scene",
    "pose_from_position_yaw_pitch",
    "scan_lidar",
    "sequence",
    "simulate_mde",
]
