"""Independent float64 NumPy reference of the frame-camera chain (tests only).

Written from the text of docs/design.md ("Conventions" and "The per-pixel chain"), NOT from
orthowarp's code: nothing here imports orthowarp's kernels, camera, pose or geodesy helpers.
ECEF <-> geodetic conversions use pyproj; the only orthowarp function used is
:func:`orthowarp.refraction.trace_delta`, for the refraction angle itself (the geometry that
applies it is ours).

Chain: pixel (col, row) -> image coordinates (mm, x right, y up, from the principal point)
-> OpenCV-normalised distorted (u, v) = (x/f, -y/f) -> Brown inverse by our own Newton
iteration with a finite-difference Jacobian -> camera ray (u, -v, -1) -> object frame
(ECEF via R_ecef<-nav R_nav<-body R_body<-cam, or the map frame via Rx(w) Ry(p) Rz(k))
-> (optionally) refraction: the chord to the point at height h is the apparent ray with its
nadir angle reduced by delta = trace_delta(theta, H, h), turned toward the local vertical at
the camera -> first crossing with the DEM found by a fine march down the heights
(<= 1/4 DEM cell along the horizontal track and <= 0.25 m in height per step) and bisection.

In geocentric mode the ray point "at height h" is the point of the chord whose exact geodetic
height (pyproj) is h; the DEM is a lon/lat (EPSG:4326) grid. In map mode it is the point of
the chord with z = h; the DEM is in the map CRS and the surface is z = DEM(x, y).
"""

import numpy as np
from pyproj import Transformer

_TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
_TO_LLH = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)

GEOCENTRIC = "geocentric"
MAP = "map"


# -- geodesy (through pyproj) and frames -----------------------------------------------------
def llh_to_ecef(lon, lat, h):
    """(lon deg, lat deg, h m) -> ECEF (..., 3) via pyproj."""
    x, y, z = _TO_ECEF.transform(np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float))
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_llh(xyz):
    """ECEF (..., 3) -> lon deg, lat deg, h m (each (...,)) via pyproj."""
    xyz = np.asarray(xyz, dtype=np.float64)
    lon, lat, h = _TO_LLH.transform(xyz[..., 0], xyz[..., 1], xyz[..., 2])
    return np.asarray(lon), np.asarray(lat), np.asarray(h)


def enu_axes(lat, lon):
    """Unit east, north, up vectors (ECEF) at geodetic lat, lon (deg), each shape (..., 3)."""
    la, lo = np.radians(lat), np.radians(lon)
    up = np.stack(np.broadcast_arrays(np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)), axis=-1)
    east = np.stack(np.broadcast_arrays(-np.sin(lo), np.cos(lo), np.zeros_like(lo)), axis=-1)
    north = np.cross(up, east)  # right-handed E, N, U
    return east, north, up


def rot_x(deg):
    """Active rotation about x by deg (counter-clockwise seen from +x)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


# Camera -> body mount: body x = camera y, body y = camera x, body z = -camera z.
MOUNT = np.column_stack([[0.0, 1.0, 0.0],    # camera x axis expressed in body axes = body y
                         [1.0, 0.0, 0.0],    # camera y -> body x
                         [0.0, 0.0, -1.0]])  # camera z -> -body z


class RefPose:
    """Camera centre, R_object<-camera, local up at the centre and the centre's height."""

    def __init__(self, mode, center, rotation, up, height):
        self.mode, self.center, self.rotation = mode, np.asarray(center, float), np.asarray(rotation, float)
        self.up, self.height = np.asarray(up, float), float(height)

    @classmethod
    def ins(cls, lat, lon, h, roll, pitch, yaw, boresight=(0.0, 0.0, 0.0), lever_arm=(0.0, 0.0, 0.0)):
        east, north, up = enu_axes(lat, lon)
        r_ecef_ned = np.column_stack([north, east, -up])
        r_ned_body = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
        r_body_cam = rot_z(boresight[2]) @ rot_y(boresight[1]) @ rot_x(boresight[0]) @ MOUNT
        center = llh_to_ecef(lon, lat, h) + r_ecef_ned @ r_ned_body @ np.asarray(lever_arm, float)
        clon, clat, ch = ecef_to_llh(center)
        cup = enu_axes(clat, clon)[2]
        return cls(GEOCENTRIC, center, r_ecef_ned @ r_ned_body @ r_body_cam, cup, ch)

    @classmethod
    def opk(cls, x, y, z, omega, phi, kappa):
        rot = rot_x(omega) @ rot_y(phi) @ rot_z(kappa)
        return cls(MAP, [x, y, z], rot, [0.0, 0.0, 1.0], z)


# -- interior orientation ---------------------------------------------------------------------
class RefCamera:
    """Frame camera: f, pixel size (mm), (W, H) px, principal point (mm), OpenCV Brown coefficients."""

    def __init__(self, f, pixel_size, size, pp=(0.0, 0.0), k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0):
        self.f = float(f)
        self.px = np.broadcast_to(np.asarray(pixel_size, float), (2,))
        self.size = np.asarray(size, float)
        self.pp = np.asarray(pp, float)
        self.k = (k1, k2, k3, p1, p2)

    def image_mm(self, pix):
        """Pixel (col, row) -> image coordinates (mm) from the principal point, x right, y up."""
        pix = np.asarray(pix, float)
        x = (pix[:, 0] - self.size[0] / 2.0) * self.px[0] - self.pp[0]
        y = (self.size[1] / 2.0 - pix[:, 1]) * self.px[1] - self.pp[1]
        return x, y

    def distort(self, u, v):
        k1, k2, k3, p1, p2 = self.k
        r2 = u * u + v * v
        rad = 1.0 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        return (u * rad + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u),
                v * rad + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v)

    def undistort(self, ud, vd):
        """Newton iteration with a central-difference Jacobian, to |residual| < 1e-15."""
        u, v = ud.copy(), vd.copy()
        e = 1e-7
        for _ in range(60):
            fu, fv = self.distort(u, v)
            ru, rv = fu - ud, fv - vd
            if np.max(np.abs(ru) + np.abs(rv)) < 1e-15:
                break
            a = (np.array(self.distort(u + e, v)) - np.array(self.distort(u - e, v))) / (2 * e)
            b = (np.array(self.distort(u, v + e)) - np.array(self.distort(u, v - e))) / (2 * e)
            det = a[0] * b[1] - b[0] * a[1]
            u = u - (b[1] * ru - b[0] * rv) / det
            v = v - (a[0] * rv - a[1] * ru) / det
        return u, v

    def rays(self, pix):
        """Pixels (N, 2) -> unit rays (N, 3) in the camera frame (x right, y up, z back)."""
        x, y = self.image_mm(pix)
        u, v = self.undistort(x / self.f, -y / self.f)
        d = np.stack([u * self.f, -v * self.f, -np.full_like(u, self.f)], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def pixels(self, rays):
        """Camera-frame directions (N, 3) -> pixels (N, 2) (closed form)."""
        rays = np.asarray(rays, float)
        u = rays[:, 0] / -rays[:, 2]
        v = -(rays[:, 1] / -rays[:, 2])
        ud, vd = self.distort(u, v)
        x, y = ud * self.f, -vd * self.f
        return np.stack([(x + self.pp[0]) / self.px[0] + self.size[0] / 2.0,
                         self.size[1] / 2.0 - (y + self.pp[1]) / self.px[1]], axis=1)


# -- DEM --------------------------------------------------------------------------------------
class GridDem:
    """North-up grid; cell (i, j) centre at (x0 + (j + .5) dx, y0 + (i + .5) dy); bilinear.

    The heights are the float32 values orthowarp stores, in float64. NaN beyond the outermost
    cell centres.
    """

    def __init__(self, array, x0, dx, y0, dy):
        self.z = np.asarray(array, dtype=np.float32).astype(np.float64)
        self.x0, self.dx, self.y0, self.dy = float(x0), float(dx), float(y0), float(dy)
        self.hmin, self.hmax = float(np.nanmin(self.z)), float(np.nanmax(self.z))

    @property
    def transform(self):
        return (self.dx, 0.0, self.x0, 0.0, self.dy, self.y0)

    def centres(self):
        rows, cols = self.z.shape
        return self.x0 + (np.arange(cols) + 0.5) * self.dx, self.y0 + (np.arange(rows) + 0.5) * self.dy

    def sample(self, x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        rows, cols = self.z.shape
        gx = (x - self.x0) / self.dx - 0.5
        gy = (y - self.y0) / self.dy - 0.5
        inside = (gx >= 0) & (gy >= 0) & (gx <= cols - 1) & (gy <= rows - 1)
        gxc = np.where(inside, gx, 0.0)
        gyc = np.where(inside, gy, 0.0)
        j = np.minimum(np.floor(gxc).astype(int), cols - 2)
        i = np.minimum(np.floor(gyc).astype(int), rows - 2)
        ax, ay = gxc - j, gyc - i
        z = ((1 - ay) * ((1 - ax) * self.z[i, j] + ax * self.z[i, j + 1])
             + ay * ((1 - ax) * self.z[i + 1, j] + ax * self.z[i + 1, j + 1]))
        return np.where(inside, z, np.nan)


# -- ray tracing ------------------------------------------------------------------------------
def turn_toward(d, n, angle):
    """Rotate unit vectors d (M, 3) by angle (M,) (rad) toward the unit vector n (3,) (Rodrigues)."""
    k = np.cross(d, n)
    s = np.linalg.norm(k, axis=1, keepdims=True)
    k = np.divide(k, s, out=np.zeros_like(k), where=s > 0)
    a = np.asarray(angle, float)[:, None]
    return d * np.cos(a) + np.cross(k, d) * np.sin(a)


class RayTracer:
    """First intersection of image rays with a DEM, float64.

    Parameters
    ----------
    pose : RefPose
    dem : GridDem
        lon/lat-degree grid (geocentric) or map-CRS grid (map mode).
    refraction : bool
        Bend rays with ``orthowarp.refraction.trace_delta``.
    """

    def __init__(self, pose, dem, refraction=False):
        self.pose, self.dem, self.refraction = pose, dem, bool(refraction)
        if pose.mode == MAP:
            self.cell_m = min(abs(dem.dx), abs(dem.dy))
        else:
            lat = np.radians(ecef_to_llh(pose.center)[1])
            self.cell_m = min(abs(dem.dy) * 110574.0, abs(dem.dx) * 111320.0 * np.cos(lat))

    def nadir_angle(self, d):
        return np.arccos(np.clip(-d @ self.pose.up, -1.0, 1.0))

    def chord(self, d, theta, h):
        """Chord direction from the camera to the ray's point at height h."""
        if not self.refraction:
            return d
        from orthowarp.refraction import trace_delta

        delta = trace_delta(theta, self.pose.height, h)
        return turn_toward(d, -self.pose.up, delta)

    def point_at(self, d, theta, h):
        """Points (M, 3) in the object frame at height h (M,) and their DEM coordinates (M, 2)."""
        d, h = np.atleast_2d(d), np.asarray(h, float)
        c = self.chord(d, theta, h)
        if self.pose.mode == MAP:
            s = (h - self.pose.center[2]) / c[:, 2]
            p = self.pose.center + s[:, None] * c
            return p, p[:, :2].copy()
        cos_t = -(c @ self.pose.up)
        s = (self.pose.height - h) / cos_t
        for _ in range(30):
            p = self.pose.center + s[:, None] * c
            lon, lat, hp = ecef_to_llh(p)
            err = hp - h
            if np.max(np.abs(err)) < 1e-8:  # ECEF float64 resolution is ~1e-9 m
                break
            n = enu_axes(lat, lon)[2]
            s = s - err / np.einsum("ij,ij->i", c, n)  # d(height)/ds = c . normal
        else:
            raise RuntimeError("height search did not converge")
        return p, np.stack([lon, lat], axis=1)

    def gap(self, d, theta, h):
        p, xy = self.point_at(d, theta, h)
        return self.dem.sample(xy[:, 0], xy[:, 1]) - h, p, xy

    def intersect(self, d):
        """Unit rays (M, 3), object frame -> first-surface points (M, 3) object frame, NaN rows on a miss."""
        d = np.atleast_2d(np.asarray(d, float))
        theta = self.nadir_angle(d)
        h_top = min(self.dem.hmax + 1.0, self.pose.height - 0.01)
        h_bot = self.dem.hmin - 1.0
        m = len(d)
        lo = np.full(m, np.nan)  # height above the crossing (gap < 0)
        hi = np.full(m, np.nan)  # height at/below the crossing (gap >= 0)
        for i in range(m):
            if not np.isfinite(theta[i]) or -d[i] @ self.pose.up <= 0.0:
                continue  # at or above the horizon
            ends, _ = self.point_at(d[[i, i]], theta[[i, i]], np.array([h_top, h_bot]))
            track = np.linalg.norm(ends[0] - ends[1]) * np.sin(theta[i])
            n = int(max(np.ceil(track / (0.25 * self.cell_m)), np.ceil((h_top - h_bot) / 0.25), 16))
            hs = np.linspace(h_top, h_bot, n + 1)
            g, _, _ = self.gap(np.repeat(d[i:i + 1], n + 1, 0), np.full(n + 1, theta[i]), hs)
            hit = np.nonzero(~(g < 0.0))[0]  # first sample not strictly above the surface (incl. NaN)
            if len(hit) == 0 or hit[0] == 0 or not np.isfinite(g[hit[0]]):
                continue  # never reaches the surface, starts below it, or leaves the DEM first
            lo[i], hi[i] = hs[hit[0] - 1], hs[hit[0]]
        ok = np.isfinite(lo)
        out = np.full((m, 3), np.nan)
        if not np.any(ok):
            return out
        a, b, dd, th = lo[ok], hi[ok], d[ok], theta[ok]
        while np.max(a - b) > 1e-7:
            mid = 0.5 * (a + b)
            g, _, _ = self.gap(dd, th, mid)
            below = g >= 0.0
            b = np.where(below, mid, b)
            a = np.where(below, a, mid)
        p, _ = self.point_at(dd, th, 0.5 * (a + b))
        out[ok] = p
        return out

    def geolocate(self, camera, pixels):
        """Pixels -> first-surface points (M, 3) in the object frame (ECEF or map x, y, z)."""
        d = camera.rays(pixels) @ self.pose.rotation.T
        return self.intersect(d)
