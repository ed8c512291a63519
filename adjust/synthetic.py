"""Synthetic blocks with known truth, for tests and benchmarks.

Strips flown along +x with ``forward`` (default 60 %) overlap along the track and ``side``
(30 %) between strips, kappa = 0; tie points at the standard (von Gruber) positions of the
images: three along the track (-base, 0, +base, so that neighbouring images share them) by
two to four rows across (see ``ties_per_image``; 9 is the classic 3 x 3 layout), or spread at
random; a smooth terrain; control-point layouts in the spirit of [P2]'s groups (``A`` well
spread: corners, edge midpoints and centre; ``B`` the four corners; ``C`` clustered at one end
of the block; ``D`` none, for GNSS-supported blocks); check points scattered over the block.
Control and check points are ground points of their own, placed independently of the tie
layout (so layouts can be compared on the same points). Image observations carry Gaussian
noise of ``sigma_px``; GNSS/INS observations, when asked for, theirs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ..camera import FrameCamera
from ..errors import ParamError
from .block import Block
from ..collinearity import project

__all__ = ["synthetic_block", "film_camera", "CONTROL_LAYOUTS"]

CONTROL_LAYOUTS = ("A", "B", "C", "D")


def film_camera() -> FrameCamera:
    """A wide-angle film camera of the kind [P2]'s blocks were flown with.

    Returns
    -------
    FrameCamera
        f = 153 mm, 230 x 230 mm format scanned at 20 um (11500 x 11500 pixels), no
        distortion.
    """
    return FrameCamera(153.0, 0.020, (11500, 11500))


def _terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The synthetic terrain's height (m) at (x, y) (m)."""
    return 300.0 + 40.0 * np.sin(x / 700.0) * np.cos(y / 900.0) + 15.0 * np.sin((x + 2 * y) / 350.0)


def synthetic_block(*, strips: int = 3, images_per_strip: int = 8, ties_per_image: int = 12,
                    control: str | ArrayLike = "A", n_check: int = 12, sigma_px: float = 0.5,
                    sigma_control: float = 0.02, gnss_sigma: float | None = None, ins_sigma: float | None = None,
                    flying_height: float = 1500.0, forward: float = 0.6, side: float = 0.3,
                    pose_noise: tuple[float, float] = (1.0, 0.05), seed: int = 0, geometry_seed: int | None = None,
                    random_ties: int | None = None, camera: FrameCamera | None = None,
                    true_camera: FrameCamera | None = None, crs: str = "EPSG:32632") -> tuple[Block, dict]:
    """A block and its truth.

    Parameters
    ----------
    strips, images_per_strip : int
    ties_per_image : {6, 9, 12}
        9: the nine standard positions (three along the track: -base, 0, +base; three across:
        the two side-overlap bands and the centre); 6: the bands only; 12: the bands and two
        rows in the image's middle third.
    control : {"A", "B", "C", "D"} or array_like (m, 2)
        A layout, or the control points' positions as fractions of the block's extent (0 at
        the first image centre / the outer edge of the first strip's side overlap, 1 at the
        last), e.g. a chosen subset of surveyed points.
    n_check : int
    sigma_px : float
        Image observation noise (px) and their stated sigma.
    sigma_control : float
        Control coordinate sigma (m) (noise and stated sigma).
    gnss_sigma, ins_sigma : float, optional
        Add GNSS projection centres (m) / INS attitudes (deg) with this noise and sigma.
    flying_height : float
        Above the mean terrain (m).
    pose_noise : (float, float)
        Perturbation of the initial poses: m and deg.
    seed : int
        Seeds the noise (and the geometry unless ``geometry_seed`` is given).
    geometry_seed : int, optional
        Seeds the geometry (tilts, point positions, check points) apart from the noise, so that
        Monte Carlo runs share one block.
    random_ties : int, optional
        Instead of the standard positions, this many tie points spread uniformly over the block
        (large blocks for benchmarks).
    camera : FrameCamera, optional
        The block's (nominal) camera; its image's first axis lies along the track. Default: a
        digital frame camera, f = 100 mm, 9 um pixels, 7000 x 10000 pixels, no distortion
        (base-to-height ratio 0.25 at 60 % overlap); :func:`film_camera` gives [P2]'s
        kind of wide-angle film camera (0.6).
    true_camera : FrameCamera, optional
        The camera that takes the images (for self-calibration tests); the block keeps the
        nominal one. Its image size must be the nominal camera's.
    crs : str, optional
        The block's CRS.

    Returns
    -------
    block : Block
    truth : dict
        ``poses`` (n, 6) (m, deg) and ``xyz`` (p, 3).
    """
    if ties_per_image not in (6, 9, 12):
        raise ParamError(f"ties_per_image must be 6, 9 or 12, got {ties_per_image!r}")
    fractions = _control_fractions(control)
    gseed = seed if geometry_seed is None else geometry_seed
    geo = np.random.default_rng([gseed, 0])  # tilts and tie points
    chk = np.random.default_rng([gseed, 1])  # check points: the same whatever the tie layout
    rng = np.random.default_rng([seed, 2])  # noise
    cam = camera or FrameCamera(100.0, 0.009, (7000, 10000))  # 7000 px along the track (x), 10000 across
    fl = _flight(cam, strips, images_per_strip, flying_height, forward, side)
    poses = _true_poses(geo, fl)
    tie_xy = _tie_positions(geo, fl, ties_per_image, random_ties)
    control_xy, check_xy = _signalised_positions(chk, fl, control, fractions, n_check)
    all_xy = np.concatenate([tie_xy, control_xy, check_xy])
    roles = ["tie"] * len(tie_xy) + ["control"] * len(control_xy) + ["check"] * n_check
    xyz = np.column_stack([all_xy, _terrain(all_xy[:, 0], all_xy[:, 1])])
    ii, jj, pix, keep = _observations(fl, poses, xyz, cam, true_camera)
    xyz, roles = xyz[keep], [r for r, k in zip(roles, keep) if k]
    n = len(poses)
    obs = pix + rng.normal(0, sigma_px, pix.shape)
    given = xyz.copy()
    rl = np.array(roles)
    given[rl == "control"] += rng.normal(0, sigma_control, ((rl == "control").sum(), 3))
    given[rl == "tie"] = np.nan
    sig = np.full((len(xyz), 3), np.nan)
    sig[rl == "control"] = sigma_control
    init = poses.copy()
    init[:, :3] += rng.normal(0, pose_noise[0], (n, 3))
    init[:, 3:] += rng.normal(0, pose_noise[1], (n, 3))
    kw = {}
    if gnss_sigma:
        kw["gnss_xyz"] = poses[:, :3] + rng.normal(0, gnss_sigma, (n, 3))
        kw["gnss_sigma"] = np.full((n, 3), float(gnss_sigma))
    if ins_sigma:
        kw["ins_opk"] = poses[:, 3:] + rng.normal(0, ins_sigma, (n, 3))
        kw["ins_sigma"] = np.full((n, 3), float(ins_sigma))
    ids = [f"s{s}_{k:03d}" for s in range(strips) for k in range(images_per_strip)]
    block = Block(crs=crs, cameras={"cam": cam}, image_ids=ids, image_camera=["cam"] * n, poses=init,
                  point_ids=[f"{r[0]}{j:05d}" for j, r in enumerate(roles)], roles=roles, xyz=given,
                  xyz_sigma=sig, obs_image=ii, obs_point=jj, obs_xy=obs, obs_sigma=np.full(len(ii), float(sigma_px)),
                  name=f"synthetic {strips}x{images_per_strip} control "
                       f"{control if fractions is None else f'{len(fractions)} points'}", **kw)
    return block, dict(poses=poses, xyz=xyz)


def _control_fractions(control: str | ArrayLike) -> np.ndarray | None:
    """Control positions given as fractions of the block's extent (k, 2), or None for a
    layout's name; ParamError for anything else."""
    fractions = None
    if not isinstance(control, str):
        fractions = np.asarray(control, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(fractions)) or np.any(np.abs(fractions - 0.5) > 1.0):
            raise ParamError(f"control positions must be finite fractions of the block's extent, got {control!r}")
    elif control not in CONTROL_LAYOUTS:
        raise ParamError(f"control must be one of {CONTROL_LAYOUTS} or positions, got {control!r}")
    return fractions


@dataclass
class _Flight:
    """The flight's geometry (m): strips along +x, images ``base`` apart along the track,
    strips ``spacing`` apart across it; an image's footprint ``along`` x ``across``; the
    cameras at height ``z0``."""

    strips: int
    images_per_strip: int
    along: float
    across: float
    base: float
    spacing: float
    z0: float


def _flight(cam: FrameCamera, strips: int, images_per_strip: int, flying_height: float, forward: float,
            side: float) -> _Flight:
    """The flight of ``cam`` at ``flying_height`` (m) above the mean terrain with ``forward``
    and ``side`` overlaps (fractions)."""
    scale = flying_height / cam.focal_length * cam.pixel_size[0]  # m per pixel
    along, across = cam.image_size[0] * scale, cam.image_size[1] * scale  # footprint (m)
    base, spacing = (1 - forward) * along, (1 - side) * across
    return _Flight(strips, images_per_strip, along, across, base, spacing, 300.0 + flying_height)


def _true_poses(geo: np.random.Generator, fl: _Flight) -> np.ndarray:
    """The true poses (n, 6; m, deg): the image centres of the strips, small random tilts."""
    centres = [(k * fl.base, s * fl.spacing) for s in range(fl.strips) for k in range(fl.images_per_strip)]
    poses = np.array([[x, y, fl.z0, 0.0, 0.0, 0.0] for x, y in centres])
    poses[:, 3:5] = geo.normal(0, 0.5, (len(poses), 2))  # small tilts (deg)
    poses[:, 5] = geo.normal(0, 0.5, len(poses))
    return poses


def _tie_positions(geo: np.random.Generator, fl: _Flight, ties_per_image: int,
                   random_ties: int | None) -> np.ndarray:
    """Tie points' ground positions (t, 2; m): the standard positions (or ``random_ties``
    spread uniformly), those inside the block's extent."""
    base, spacing, along, across = fl.base, fl.spacing, fl.along, fl.across
    strips, images_per_strip = fl.strips, fl.images_per_strip
    rows = {6: [-0.5, 0.5], 9: [-0.5, 0.0, 0.5], 12: [-0.5, -1 / 6, 1 / 6, 0.5]}[ties_per_image]
    pts = {}
    for s in range(strips):
        for k in range(-1, images_per_strip + 1):
            for r in rows:
                key = (k, round((s + r) * 6))
                if key not in pts:
                    x = k * base + geo.uniform(-0.05, 0.05) * base
                    y = (s + r) * spacing + geo.uniform(-0.03, 0.03) * spacing
                    pts[key] = (x, y)
    tie_xy = np.array(list(pts.values()))
    if random_ties:
        tie_xy = np.stack([geo.uniform(-0.4 * along, (images_per_strip - 1) * base + 0.4 * along, int(random_ties)),
                           geo.uniform(-0.4 * across, (strips - 1) * spacing + 0.4 * across, int(random_ties))], 1)
    x0, x1 = -0.4 * along, (images_per_strip - 1) * base + 0.4 * along
    y0, y1 = -0.4 * across, (strips - 1) * spacing + 0.4 * across
    inside = (tie_xy[:, 0] > x0) & (tie_xy[:, 0] < x1) & (tie_xy[:, 1] > y0) & (tie_xy[:, 1] < y1)
    return tie_xy[inside]


def _signalised_positions(chk: np.random.Generator, fl: _Flight, control: str | ArrayLike,
                          fractions: np.ndarray | None, n_check: int) -> tuple[np.ndarray, np.ndarray]:
    """Control (c, 2) and check (n_check, 2) points' ground positions (m): ground points of
    their own (signalised), placed whatever the tie layout."""
    base, spacing, strips = fl.base, fl.spacing, fl.strips
    # the control layouts' target positions
    xa, xb = 0.0, (fl.images_per_strip - 1) * base
    ya, yb = -0.5 * spacing, (strips - 0.5) * spacing
    targets = {"A": [(xa, ya), (xb, ya), (xa, yb), (xb, yb), ((xa + xb) / 2, ya), ((xa + xb) / 2, yb),
                     (xa, (ya + yb) / 2), (xb, (ya + yb) / 2), ((xa + xb) / 2, (ya + yb) / 2)],
               "B": [(xa, ya), (xb, ya), (xa, yb), (xb, yb)],
               "C": [(xa, ya), (xa + base, ya), (xa, ya + spacing), (xa + base, ya + spacing)],
               "D": []}[control] if fractions is None else \
        [(xa + fx * (xb - xa), ya + fy * (yb - ya)) for fx, fy in fractions]
    # control and check points are ground points of their own (signalised), placed whatever
    # the tie layout, and measured in every image that sees them
    control_xy = np.array(targets, float).reshape(-1, 2) + chk.uniform(-0.02, 0.02, (len(targets), 2)) * base
    check_xy = np.stack([chk.uniform(xa, xb, n_check), chk.uniform(0.0, (strips - 1) * spacing, n_check)], 1)
    return control_xy, check_xy


def _observations(fl: _Flight, poses: np.ndarray, xyz: np.ndarray, cam: FrameCamera,
                  true_camera: FrameCamera | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every point (p, 3; m) in every image it falls in (50 px from the border), taken by
    ``true_camera`` (else ``cam``) at ``poses`` (n, 6; m, deg), points seen at least twice:
    images (m,), points (m,) numbered among the kept ones, exact pixels (m, 2), and which
    points are kept (p,)."""
    base, spacing, along, across = fl.base, fl.spacing, fl.along, fl.across
    images_per_strip, strips = fl.images_per_strip, fl.strips
    p = len(xyz)
    # candidate images of each point: the grid neighbours of its nearest image centre
    kk = np.rint(xyz[:, 0] / base).astype(int)
    ss = np.rint(xyz[:, 1] / spacing).astype(int)
    reach_k, reach_s = int(np.ceil(0.5 * along / base)) + 1, int(np.ceil(0.5 * across / spacing)) + 1
    cand_i, cand_j = [], []
    for dk in range(-reach_k, reach_k + 1):
        for ds in range(-reach_s, reach_s + 1):
            k, s_ = kk + dk, ss + ds
            ok = (k >= 0) & (k < images_per_strip) & (s_ >= 0) & (s_ < strips)
            cand_i.append((s_ * images_per_strip + k)[ok])
            cand_j.append(np.flatnonzero(ok))
    ii, jj = np.concatenate(cand_i), np.concatenate(cand_j)
    pr = poses.copy()
    pr[:, 3:] = np.radians(pr[:, 3:])
    shoot = true_camera or cam
    if tuple(shoot.image_size) != tuple(cam.image_size):
        raise ParamError(f"true_camera must be {cam.image_size[0]} x {cam.image_size[1]} pixels")
    cam_row = np.array([[shoot.focal_length, *shoot.principal_point, shoot.k1, shoot.k2, shoot.k3, shoot.p1,
                         shoot.p2, *shoot.pixel_size]])
    size = np.array([cam.image_size], float)
    pix = project(pr[ii], xyz[jj], np.repeat(cam_row, len(ii), 0), np.repeat(size, len(ii), 0))
    margin = 50
    ok = ((pix[:, 0] > margin) & (pix[:, 0] < cam.image_size[0] - margin) & (pix[:, 1] > margin)
          & (pix[:, 1] < cam.image_size[1] - margin))
    ii, jj, pix = ii[ok], jj[ok], pix[ok]
    counts = np.bincount(jj, minlength=p)
    keep = counts >= 2
    remap = -np.ones(p, int)
    remap[keep] = np.arange(keep.sum())
    sel = keep[jj]
    return ii[sel], remap[jj[sel]], pix[sel], keep
