"""The SPOT pushbroom model (float64 host reference) on the real SPOT-5 sample."""

import os

import numpy as np
import pytest

from orthowarp import PushbroomScene
from orthowarp.errors import GeometryError, ParamError
from orthowarp.geodesy import geodetic_to_ecef
from orthowarp.pipeline.dimap import read_dimap
from orthowarp.pushbroom import attitude_matrix, lagrange

SAMPLE = os.path.join(os.path.dirname(__file__), "data", "spot5", "spot_example1.xml")


@pytest.fixture(scope="module")
def scene():
    return PushbroomScene.from_dimap(SAMPLE)


def test_corners_reproduce_the_dataset_frame(scene):
    """The Dataset_Frame vertices of column 1 (rows 1 and 96168, DIMAP numbering at pixel
    centres) are the scene's corners located on the ellipsoid: < 1 m (measured: 2.7, 3.7 cm)."""
    m = read_dimap(SAMPLE)
    verts = [v for v in m.frame if v["col"] == 1]
    assert len(verts) == 2
    pix = np.array([[v["col"] - 0.5, v["row"] - 0.5] for v in verts])
    g = scene.geolocate_ellipsoid(pix, 0.0)
    ours = geodetic_to_ecef(g[:, 1], g[:, 0], 0.0)
    theirs = geodetic_to_ecef([v["lat"] for v in verts], [v["lon"] for v in verts], 0.0)
    dist = np.linalg.norm(ours - theirs, axis=1)
    # the vertices are given to 1e-6 degrees: 0.11 m in latitude
    assert np.all(dist < 0.1), dist
    np.testing.assert_allclose(g[:, 2], 0.0, atol=1e-6)


def test_lagrange_is_exact_at_nodes_and_for_polynomials():
    t = np.linspace(0, 30 * 12, 13)
    vals = np.stack([1 + 2 * t - 3e-3 * t**2 + 1e-7 * t**7, np.cos(t / 50)], -1)
    np.testing.assert_allclose(lagrange(t, t, vals), vals, rtol=1e-12)
    tq = np.linspace(0, 360, 101)
    np.testing.assert_allclose(lagrange(tq, t, vals)[:, 0], (1 + 2 * tq - 3e-3 * tq**2 + 1e-7 * tq**7), rtol=1e-9, atol=1e-6)


def test_interpolated_velocity_is_the_derivative_of_the_position(scene):
    """Position and velocity are interpolated independently: the velocity must agree with the
    derivative of the interpolated position (an independent consistency check of the file and
    the interpolation)."""
    t = np.linspace(-36, 36, 25)
    dt = 1e-3
    p1, _ = scene.orbit(t - dt)
    p2, _ = scene.orbit(t + dt)
    _, v = scene.orbit(t)
    np.testing.assert_allclose((p2 - p1) / (2 * dt), v, atol=2e-3)  # m/s of ~7.4 km/s
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 7.5e3, rtol=5e-3)  # ECEF (Earth-fixed) speed
    # altitude of ~830 km over Antarctica
    assert np.all(np.abs(np.linalg.norm(scene.orbit(t)[0], axis=1) - 6.36e6 - 8.3e5) < 3e4)


def test_attitude_matrix_forms():
    y, p, r = 1.2e-3, -9.5e-4, 3e-4
    m = attitude_matrix(y, p, r)[0]
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-15)
    # M = Mp Mr My with elementary rotations (handbook eq. 11), built independently
    my = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    mr = np.array([[np.cos(r), 0, -np.sin(r)], [0, 1, 0], [np.sin(r), 0, np.cos(r)]])
    mp = np.array([[1, 0, 0], [0, np.cos(p), np.sin(p)], [0, -np.sin(p), np.cos(p)]])
    np.testing.assert_allclose(m, mp @ mr @ my, atol=1e-15)
    first = attitude_matrix(y, p, r, first_order=True)[0]
    assert np.max(np.abs(first - m)) < 2e-6  # second-order terms of milliradian angles


def test_first_order_attitude_model_differs_by_second_order_terms(scene):
    fo = PushbroomScene.from_dimap(SAMPLE, attitude_model="first_order")
    pix = np.array([[0.5, 0.5], [150.0, 48084.5], [299.5, 96167.5]])
    a = geodetic_to_ecef(*scene.geolocate_ellipsoid(pix)[:, [1, 0, 2]].T)
    b = geodetic_to_ecef(*fo.geolocate_ellipsoid(pix)[:, [1, 0, 2]].T)
    d = np.linalg.norm(a - b, axis=1)
    assert np.all(d < 5.0) and np.all(d > 0.0)


def test_times_outside_the_ephemeris_are_errors(scene):
    with pytest.raises(GeometryError, match="outside the ephemeris"):
        scene.geolocate_ellipsoid(np.array([[10.0, 1e6]]))
    with pytest.raises(GeometryError, match="outside the attitudes"):
        scene.orbit(np.array([-100.0]))
    with pytest.raises(ParamError, match="attitude_model"):
        PushbroomScene.from_dimap(SAMPLE, attitude_model="quaternion")
    with pytest.raises(ParamError, match="pixels"):
        scene.geolocate_ellipsoid(np.array([[np.nan, 1.0]]))
