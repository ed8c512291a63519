"""Independent float64 NumPy renderer of synthetic aerial frame images (tests only).

Given a camera and a pose (the conventions of docs/design.md, as :mod:`reference` implements them from
the text: :class:`reference.RefCamera`, :class:`reference.RefPose`), a DEM surface and an
analytic, band-limited texture T(x, y) on the ground, :class:`Renderer` draws the image the
camera would take: for every pixel (a few sub-pixel samples each, so that a pixel is the
average of the ground it sees, like a real sensor) it casts the ray, intersects it with the
DEM, and reads T there. Nothing here uses orthowarp's kernels, camera, pose or geometry; the
only orthowarp function used is :func:`orthowarp.refraction.trace_delta` (the refraction angle
itself; the geometry that applies it is ours, as in :mod:`reference`).

Unlike :class:`reference.RayTracer`, which runs one ray at a time, the renderer is vectorised
over all rays (a few hundred thousand per image):

* Rays: pixel -> distorted normalised coordinates -> Brown inverse by the reference's own
  Newton iteration -> camera ray -> object frame (ECEF or map x, y, z).
* Refraction (optional): the chord from the camera to the ray's point at height h is the
  apparent ray turned toward the nadir by delta(theta, h) = ``trace_delta(theta, H, h)``
  (theta the apparent nadir angle at the camera, H the camera's height); delta is read from a
  bicubic spline fitted to ``trace_delta`` on a fine (theta, h) grid spanning the rays (its
  interpolation error is checked against ``trace_delta`` itself: below 1e-10 rad, 1e-7 m
  per km of slant range).
* Surface: the rays are parameterised by the height h of their point. In map mode that point
  is where the chord reaches z = h; in geocentric mode where it reaches geodetic height h: a
  closed-form intersection with the ellipsoid of semi-axes (a + h, b + h) (good to ~1 mm)
  refined by Newton steps on the exact geodetic height from pyproj.
* Intersection: a march down the heights from above the DEM's highest point, in steps that
  move the ray's foot by at most ``march_step`` m horizontally, brackets the first crossing
  DEM(x, y) = h (the march uses the closed-form points, the bracket is widened by 5 cm to
  absorb their error); Illinois regula falsi on the exact points then narrows the bracket to
  1e-7 m in height or finds |gap| < 1e-8 m.
* Texture: evaluated at the ground point's coordinates in the texture's projected CRS
  (pyproj from longitude/latitude in geocentric mode; the map CRS itself in map mode).
"""

import numpy as np
from pyproj import Transformer
from scipy.interpolate import RectBivariateSpline

try:
    from . import reference as ref
except ImportError:
    import reference as ref

WGS84_A = 6378137.0
WGS84_B = WGS84_A * (1.0 - 1.0 / 298.257223563)


class Texture:
    """A band-limited random texture T(x, y) in a projected CRS (metres).

    A sum of ``n`` cosines with random directions, phases and amplitudes, and periods between
    ``min_period`` and ``max_period`` metres (at >= 8 ground sample distances it is well
    sampled by the images and the orthoimages), plus a constant ``offset``. Coordinates are
    taken relative to ``origin`` for float64 headroom.
    """

    def __init__(self, origin, *, min_period, max_period, n=32, amplitude=100.0, offset=1000.0, seed=0):
        rng = np.random.default_rng(seed)
        self.origin = np.asarray(origin, dtype=np.float64)
        period = np.exp(rng.uniform(np.log(min_period), np.log(max_period), n))
        angle = rng.uniform(0.0, np.pi, n)
        self.k = np.stack([np.cos(angle), np.sin(angle)], axis=1) / period[:, None]  # cycles / m
        self.phase = rng.uniform(0.0, 2.0 * np.pi, n)
        self.amp = amplitude * rng.uniform(0.5, 1.0, n) / np.sqrt(n / 2.0)
        self.offset = float(offset)
        self.min_period, self.max_period = float(min_period), float(max_period)

    def __call__(self, x, y):
        x = np.asarray(x, dtype=np.float64) - self.origin[0]
        y = np.asarray(y, dtype=np.float64) - self.origin[1]
        out = np.full(np.broadcast(x, y).shape, self.offset)
        for (kx, ky), ph, a in zip(self.k, self.phase, self.amp):
            out += a * np.cos(2.0 * np.pi * (kx * x + ky * y) + ph)
        return out

    @property
    def std(self):
        """Standard deviation of T over the plane."""
        return float(np.sqrt(0.5 * np.sum(self.amp**2)))


def ellipsoid_intersection(center, c, h):
    """Distance s along unit chords c (M, 3) from ``center`` (3,) to the ellipsoid of semi-axes
    (a + h, a + h, b + h), nearer root; NaN where the chord misses it."""
    big_a, big_b = WGS84_A + h, WGS84_B + h
    q = np.stack([1.0 / big_a**2, 1.0 / big_a**2, 1.0 / big_b**2], axis=1)  # x^2/A^2 + y^2/A^2 + z^2/B^2 = 1
    qa = np.sum(q * c * c, axis=1)
    qb = 2.0 * np.sum(q * c * center[None, :], axis=1)
    qc = np.sum(q * center[None, :] ** 2, axis=1) - 1.0
    disc = qb * qb - 4.0 * qa * qc
    with np.errstate(invalid="ignore"):
        root = np.sqrt(disc)
        # stable nearer root: qc > 0 (outside), qb < 0 (pointing toward the surface)
        s = (2.0 * qc) / (-qb + root)
    return np.where(disc >= 0.0, s, np.nan)


class Renderer:
    """Ray caster and image renderer.

    Parameters
    ----------
    camera : reference.RefCamera
    pose : reference.RefPose
    dem : callable (x, y) -> z
        The terrain in the DEM frame: longitude/latitude (deg) and ellipsoidal height in
        geocentric mode, map x/y/z in map mode (e.g. ``reference.GridDem.sample``, the same
        bilinear surface orthowarp reads from the grid). NaN where undefined.
    h_range : (float, float)
        Lowest and highest terrain height (m).
    texture : callable (x, y) -> value
        The ground texture in ``texture_crs``.
    texture_crs : str
        Projected CRS of the texture (in map mode it must be the pose's map CRS).
    refraction : bool, optional
        Bend the rays with ``orthowarp.refraction.trace_delta``.
    march_step : float, optional
        Largest horizontal move (m) of the ray's foot per step of the march.
    """

    def __init__(self, camera, pose, dem, h_range, texture, texture_crs, *, refraction=False,
                 march_step=2.0):
        self.camera, self.pose, self.dem = camera, pose, dem
        self.h_bot, self.h_top = float(h_range[0]) - 1.0, min(float(h_range[1]) + 1.0, pose.height - 0.01)
        self.texture = texture
        self.refraction = bool(refraction)
        self.march_step = float(march_step)
        self.geocentric = pose.mode == ref.GEOCENTRIC
        self._to_tex = (Transformer.from_crs("EPSG:4326", texture_crs, always_xy=True)
                        if self.geocentric else None)
        self._delta = None

    # -- refraction -------------------------------------------------------------------------
    def _delta_spline(self):
        """Bicubic spline of trace_delta over the image's nadir angles (+-1 deg) and the heights."""
        from orthowarp.refraction import trace_delta

        w, h = self.camera.size
        c, r = np.meshgrid(np.linspace(0.0, w, 21), np.linspace(0.0, h, 21))
        theta = self.nadir_angle(self.rays(np.stack([c.ravel(), r.ravel()], axis=1)))
        theta = np.concatenate([theta, [0.0]]) if self._sees_nadir() else theta
        pad = np.radians(1.0)
        ts = np.linspace(max(theta.min() - pad, 0.0), theta.max() + pad, 64)
        hs = np.linspace(self.h_bot - 5.0, self.h_top + 5.0, 12)
        table = trace_delta(ts[:, None], self.pose.height, hs[None, :])
        spline = RectBivariateSpline(ts, hs, table, kx=3, ky=3)
        # its interpolation error, at points between the nodes
        tm, hm = 0.5 * (ts[1:] + ts[:-1]), 0.5 * (hs[1:] + hs[:-1])
        err = np.abs(spline(tm, hm) - trace_delta(tm[:, None], self.pose.height, hm[None, :]))
        assert err.max() < 1e-10, f"refraction spline error {err.max():.2e} rad"
        return spline, (ts[0], ts[-1])

    def _sees_nadir(self):
        """Whether the nadir direction falls inside the image (then theta reaches 0)."""
        down = self.pose.rotation.T @ -self.pose.up  # camera frame
        if down[2] >= 0.0:
            return False
        col, row = self.camera.pixels(down[None, :])[0]
        return 0.0 <= col <= self.camera.size[0] and 0.0 <= row <= self.camera.size[1]

    def delta(self, theta, h):
        """Refraction angle (rad) at apparent nadir angle theta (rad) and height h (m)."""
        if self._delta is None:
            self._delta = self._delta_spline()
        spline, (t0, t1) = self._delta
        assert np.all((theta >= t0) & (theta <= t1)), "ray outside the refraction spline's range"
        return spline.ev(theta, h)

    # -- points on the rays -----------------------------------------------------------------
    def nadir_angle(self, d):
        return np.arccos(np.clip(-(d @ self.pose.up), -1.0, 1.0))

    def bundle(self, d):
        """Per-ray constants: unit rays d (M, 3), apparent nadir angles theta (M,), and for
        refraction the unit vector w (M, 3) in the plane of d and the nadir, perpendicular to d
        and on the nadir side, so that the ray turned toward the nadir by delta is
        d cos(delta) + w sin(delta) (the Rodrigues rotation of reference.turn_toward)."""
        d = np.atleast_2d(np.asarray(d, dtype=np.float64))
        theta = self.nadir_angle(d)
        w = None
        if self.refraction:
            w = np.cross(np.cross(d, -self.pose.up), d)
            norm = np.linalg.norm(w, axis=1, keepdims=True)
            w = np.divide(w, norm, out=np.zeros_like(w), where=norm > 0)
        return d, theta, w

    def chord(self, rays, h):
        d, theta, w = rays
        if not self.refraction:
            return d
        delta = self.delta(theta, h)[:, None]
        return d * np.cos(delta) + w * np.sin(delta)

    def point_at(self, rays, h, *, exact=True):
        """Points (M, 3) of the object frame where the rays reach height h (M,), and their
        DEM-frame horizontal coordinates (M, 2) (lon/lat deg or map x/y).

        Geocentric mode with ``exact=False``: the point on the ellipsoid (a + h, b + h)
        (about 1 mm from geodetic height h), for the march only.
        """
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(rays[0]),))
        c = self.chord(rays, h)
        center = self.pose.center
        if not self.geocentric:
            s = (h - center[2]) / c[:, 2]
            p = center[None, :] + s[:, None] * c
            return p, p[:, :2]
        s = ellipsoid_intersection(center, c, h)
        p = center[None, :] + s[:, None] * c
        for _ in range(6):
            lon, lat, hp = ref.ecef_to_llh(p)
            err = hp - h
            if not exact or not np.nanmax(np.abs(err), initial=0.0) >= 1e-7:
                return p, np.stack([lon, lat], axis=1)
            la, lo = np.radians(lat), np.radians(lon)
            cos_la = np.cos(la)
            dh_ds = c[:, 0] * cos_la * np.cos(lo) + c[:, 1] * cos_la * np.sin(lo) + c[:, 2] * np.sin(la)
            s = s - err / dh_ds  # d(height)/ds = c . ellipsoid normal
            p = center[None, :] + s[:, None] * c
        raise RuntimeError("geodetic height search did not converge")

    def gap(self, rays, h, *, exact=True):
        """DEM height minus h at the rays' points of height h (> 0: the point is underground)."""
        p, xy = self.point_at(rays, h, exact=exact)
        return self.dem(xy[:, 0], xy[:, 1]) - h, p, xy

    def intersect(self, d):
        """Unit rays (M, 3) (object frame) -> first-surface points (M, 3) and their DEM-frame
        horizontal coordinates (M, 2); NaN rows where a ray misses the DEM."""
        rays = self.bundle(d)
        m = len(rays[0])
        # march: steps that move the foot by <= march_step m horizontally (widest ray)
        track = (self.h_top - self.h_bot) * np.tan(np.max(rays[1])) * 1.1
        n = int(max(6, np.ceil(track / self.march_step)))
        hs = np.linspace(self.h_top, self.h_bot, n + 1)
        first = np.full(m, -1)
        above = None  # rays still strictly above the surface at the previous level
        for k, h in enumerate(hs):
            g, _, _ = self.gap(rays, np.full(m, h), exact=False)
            if k == 0:
                above = g < 0.0  # a ray that starts below the surface never hits
                continue
            hit = above & ~(g < 0.0)  # first level at/below the surface, or off the DEM
            first[hit] = k
            above &= g < 0.0
        out = np.full((m, 3), np.nan)
        out_xy = np.full((m, 2), np.nan)
        sel = np.nonzero(first > 0)[0]
        # bracket [lo, hi] in height, widened by 5 cm for the march's approximate points
        hi = hs[first[sel] - 1] + 0.05
        lo = hs[first[sel]] - 0.05
        sub = tuple(None if v is None else v[sel] for v in rays)
        g_lo, _, _ = self.gap(sub, lo)
        g_hi, _, _ = self.gap(sub, hi)
        good = (g_hi < 0.0) & (g_lo >= 0.0)  # a clean bracket (NaN at lo: the ray leaves the DEM)
        sel, hi, lo, g_hi, g_lo = sel[good], hi[good], lo[good], g_hi[good], g_lo[good]
        sub = tuple(None if v is None else v[good] for v in sub)
        # Illinois (modified regula falsi) on the exact gap: superlinear, keeps the bracket
        best = 0.5 * (hi + lo)
        done = np.zeros(len(sel), bool)
        side = np.zeros(len(sel), np.int8)  # which end moved last: +1 lo, -1 hi
        for _ in range(100):
            if done.all():
                break
            with np.errstate(invalid="ignore", divide="ignore"):
                t = g_hi / (g_hi - g_lo)  # fraction of the way from hi to lo where the gap vanishes
            mid = hi + np.where(np.isfinite(t), np.clip(t, 0.0, 1.0), 0.5) * (lo - hi)
            g, _, _ = self.gap(sub, mid)
            below = ~(g < 0.0)
            # Illinois: an end that stays twice in a row gets its gap halved
            g_hi = np.where(below, np.where(side == 1, 0.5 * g_hi, g_hi), g)
            g_lo = np.where(below, g, np.where(side == -1, 0.5 * g_lo, g_lo))
            side = np.where(below, 1, -1).astype(np.int8)
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
            best = np.where(done, best, mid)
            done |= (np.abs(g) < 1e-8) | (hi - lo < 1e-7)
        else:
            raise RuntimeError("surface search did not converge")
        p, xy = self.point_at(sub, best)
        out[sel], out_xy[sel] = p, xy
        return out, out_xy

    # -- images -----------------------------------------------------------------------------
    def rays(self, pixels):
        """Pixels (N, 2) (col, row) -> unit rays (N, 3) in the object frame."""
        return self.camera.rays(np.asarray(pixels, dtype=np.float64)) @ self.pose.rotation.T

    def ground(self, pixels):
        """Pixels (N, 2) -> ground points: object frame (N, 3), texture-CRS x/y (N, 2)."""
        p, xy = self.intersect(self.rays(pixels))
        return p, self.to_texture(xy)

    def to_texture(self, xy):
        """DEM-frame horizontal coordinates (N, 2) -> texture-CRS x/y (N, 2)."""
        if not self.geocentric:
            return np.asarray(xy, dtype=np.float64)
        x, y = self._to_tex.transform(xy[:, 0], xy[:, 1])
        return np.stack([x, y], axis=1)

    def render(self, supersample=2):
        """The image (rows, cols) float64: each pixel the mean of T over supersample^2 points
        on a regular grid inside it. Raises if a ray misses the DEM."""
        w, h = (int(v) for v in self.camera.size)
        sub = (np.arange(supersample) + 0.5) / supersample
        jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        acc = np.zeros((h, w))
        for a in sub:
            for b in sub:
                pix = np.stack([(jj + b).ravel(), (ii + a).ravel()], axis=1)
                _, txy = self.ground(pix)
                if not np.all(np.isfinite(txy)):
                    raise AssertionError(f"{np.sum(~np.isfinite(txy[:, 0]))} rays miss the DEM")
                acc += self.texture(txy[:, 0], txy[:, 1]).reshape(h, w)
        return acc / supersample**2
