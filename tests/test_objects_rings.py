"""An object seen on one or two of the sensor's rings has no motion of its own to register
(``ssf.objects.min_rings``): a tree's canopy, rebuilt with exact ray casting from two
sensor positions 0.8 m apart, whose two flagged ring arcs the objects' ICP slid onto scan
k's neighbouring arcs and called moving (fresh simulated ``static`` 784, stop 66). Real
compiled ICP, real SciPy KD-trees; the ring count on hand-computed cases."""

import numpy as np
import pytest

from flowslam import geometry
from flowslam.config import ObjectRefinementConfig
from flowslam.sceneflow.refinement.clusters import LocalGround, ring_count
from flowslam.sceneflow.refinement.objects import refine_objects

DT = 0.1
HEIGHT = 1.73  # sensor above the flat ground (m)
STEP_M = 0.8  # the ego's forward step per scan (m)
T_EGO = geometry.inv(geometry.from_euler("z", 0.0, t=[STEP_M, 0.0, 0.0]))  # T_{k,k-1}
ELEVATIONS_DEG = [-15.0, -11.0, -8.0, -6.0, -4.5, -3.0, -2.0, -1.0, 0.0, 1.0, 2.3, 3.3, 4.7, 7.0, 10.3, 15.0]
CANOPY_CENTRE = np.array([16.0, 3.0, 5.0])  # world frame (m), the ground at z = 0
CANOPY_RADIUS_M = 2.0


def _rays(elevations_deg, step_deg: float) -> np.ndarray:
    """(N,3) unit directions of a spinning sensor's rings, one per ``step_deg`` of azimuth."""
    az, el = np.meshgrid(np.radians(np.arange(-180.0, 180.0, step_deg)), np.radians(elevations_deg))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def _returns(d: np.ndarray, t_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The returns (sensor frame, m; within 60 m) of rays ``d`` from a sensor HEIGHT above
    flat ground, given each ray's distance to an object (inf: misses it), and whether each
    return is on the object."""
    t = np.full(len(d), np.inf)
    down = d[:, 2] < 0
    t[down] = HEIGHT / -d[down, 2]
    on_object = (t_object > 0) & (t_object < t)
    t = np.where(on_object, t_object, t)
    keep = t < 60.0
    return d[keep] * t[keep, None], on_object[keep]


def _cast(x: float) -> tuple[np.ndarray, np.ndarray]:
    """One scan of a sensor at (x, 0, HEIGHT), axes as the world's: its rings (every 0.2 deg
    of azimuth) against flat ground and a spherical canopy. Returns the points (sensor frame,
    m; returns within 60 m) and whether each is on the canopy."""
    d = _rays(ELEVATIONS_DEG, 0.2)
    oc = np.array([x, 0.0, HEIGHT]) - CANOPY_CENTRE
    b = d @ oc
    disc = b * b - (oc @ oc - CANOPY_RADIUS_M ** 2)
    return _returns(d, np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf))


def _cast_post(x: float, centre_xy, radius: float, z_range) -> tuple[np.ndarray, np.ndarray]:
    """A 16-beam sensor (rings 2 deg apart, every 0.1 deg of azimuth) at (x, 0, HEIGHT)
    against flat ground and a vertical cylinder (``radius``, world heights ``z_range``, m):
    the returns and whether each is on the cylinder (:func:`_returns`)."""
    d = _rays(np.arange(-15.0, 16.0, 2.0), 0.1)
    o = np.array([x, 0.0]) - np.asarray(centre_xy)
    a = np.einsum("ij,ij->i", d[:, :2], d[:, :2])
    b = 2.0 * d[:, :2] @ o
    disc = b * b - 4.0 * a * (o @ o - radius ** 2)
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a), np.inf)
    z = HEIGHT + t * d[:, 2]
    return _returns(d, np.where((z >= z_range[0]) & (z <= z_range[1]), t, np.inf))


def _elevations_deg(points: np.ndarray) -> np.ndarray:
    return np.round(np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))), 3)


def _refine(prev: np.ndarray, curr: np.ndarray, dynamic: np.ndarray, **options):
    c = ObjectRefinementConfig(**options)
    ev = c.motion_evidence
    flow = geometry.rigid_flow(T_EGO, prev)  # the network's flow: the ego motion's
    above = LocalGround(prev, ev.ground_cell_m).above(ev.ground_clearance_m)
    return refine_objects(prev, flow, dynamic.copy(), curr, T_EGO, DT, c, above_ground=above)


def test_ring_count_on_hand_built_rings():
    az = np.radians(np.linspace(10.0, 12.0, 21))
    ranges = np.linspace(15.0, 18.0, 21)  # one ring over a varying range: one elevation

    def ring(elevation_deg: float) -> np.ndarray:
        e = np.radians(elevation_deg)
        return np.stack([ranges * np.cos(e) * np.cos(az), ranges * np.cos(e) * np.sin(az),
                         ranges * np.sin(e)], axis=1)

    gap = np.radians(0.1)
    assert ring_count(ring(2.0), gap) == 1
    assert ring_count(np.concatenate([ring(2.0), ring(2.33), ring(2.66)]), gap) == 3
    assert ring_count(np.concatenate([ring(2.0), ring(2.05)]), gap) == 1  # 0.05 deg apart: one ring at 0.1 deg
    assert ring_count(np.concatenate([ring(2.0), ring(2.05)]), np.radians(0.04)) == 2
    assert ring_count(np.zeros((0, 3)), gap) == 0
    # no ring structure: elevations spread evenly over 2 deg count one ring per 0.1 deg of it
    spread = np.concatenate([ring(e) for e in np.linspace(1.0, 3.0, 81)])  # 0.025 deg apart
    assert ring_count(spread, gap) == 21


@pytest.fixture(scope="module")
def canopy_scans():
    prev, canopy = _cast(0.0)
    curr, _ = _cast(STEP_M)
    return prev, curr, canopy


def test_a_static_canopy_on_two_rings_stays_static(canopy_scans):
    prev, curr, canopy = canopy_scans
    elevation = _elevations_deg(prev)
    rings = np.unique(elevation[canopy])
    assert len(rings) == 4  # the canopy holds four of the sensor's rings
    flagged = canopy & np.isin(elevation, rings[:2])  # a false flag on its two lowest arcs
    assert flagged.sum() >= 50 and ring_count(prev[flagged], np.radians(0.1)) == 2

    # without the test: the ego landings fall between scan k's arcs (static RMSE ~9 cm),
    # and the ICP slides the two arcs onto them, a "motion" of ~1.4 m/s
    slid = _refine(prev, curr, flagged, min_rings=0)  # (each call states its ring settings)
    assert slid.dynamic[flagged].mean() > 0.9
    assert slid.objects[0]["static_rmse_m"] > 0.05 and slid.objects[0]["rmse_m"] < 0.03
    assert 0.5 < slid.objects[0]["speed_mps"] < 3.0

    for body_m in (0.0, 1.5):  # the two arcs are also a slice of a body on four rings
        kept = _refine(prev, curr, flagged, min_rings=3, ring_body_m=body_m)
        assert not kept.dynamic.any()
        assert kept.objects[0]["few_rings"] and "fitness" not in kept.objects[0]  # no ICP ran
        assert np.allclose(kept.flow[flagged], geometry.rigid_flow(T_EGO, prev[flagged]))


def test_an_object_on_enough_rings_still_gets_its_icp(canopy_scans):
    """The test only asks for rings: the whole canopy (four rings) is registered as before
    (and, flagged whole, this sparse sphere still slides: the ring test does not cover it)."""
    prev, curr, canopy = canopy_scans
    before = _refine(prev, curr, canopy, min_rings=0)
    after = _refine(prev, curr, canopy, min_rings=3)
    assert "fitness" in after.objects[0] and "few_rings" not in after.objects[0]
    assert np.array_equal(before.dynamic, after.dynamic)
    assert np.allclose(before.flow, after.flow)


def test_an_object_thin_as_a_whole_keeps_its_icp_with_the_body_test():
    """A 16-beam sensor's rings are 2 deg apart: a torso-sized post 15 m away (0.3 m radius,
    0.7-1.7 m above the ground) is seen on two rings, with nothing else clear of the ground
    within 1.5 m. Flagged whole and moving 0.5 m away from the sensor, it loses its ICP to
    the plain ring test; ``ring_body_m`` finds no thicker body around it and leaves it as
    without the test (what the other tests then make of its motion is not asserted here)."""
    prev, post = _cast_post(0.0, (15.0, 0.0), 0.3, (0.7, 1.7))
    curr, _ = _cast_post(STEP_M, (15.5, 0.0), 0.3, (0.7, 1.7))
    assert post.sum() >= 40 and ring_count(prev[post], np.radians(0.1)) == 2

    plain = _refine(prev, curr, post, min_rings=3, ring_body_m=0.0)
    assert plain.objects[0]["few_rings"] and "fitness" not in plain.objects[0]

    without = _refine(prev, curr, post, min_rings=0)
    body = _refine(prev, curr, post, min_rings=3, ring_body_m=1.5)
    assert "few_rings" not in body.objects[0] and body.objects[0]["fitness"] == without.objects[0]["fitness"]
    assert np.array_equal(body.dynamic, without.dynamic) and np.allclose(body.flow, without.flow)
