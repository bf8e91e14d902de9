"""Contact with the static world (services/simulator/contact.py) against python-fcl's distances, the
oracle: a UAV's body sphere at many random points outside each primitive; and hand cases inside
(negative) and on the surface."""
from __future__ import annotations

import math

import fcl
import numpy as np
import pytest
from scipy.optimize import minimize

from schemas.messages import Obstacle
from services.simulator import contact

BODY = 0.4
SHAPES = {
    "box": Obstacle(kind="box", center=(3.0, -2.0, 4.0), size=(10.0, 8.0, 6.0), name="building"),
    "cylinder": Obstacle(kind="cylinder", center=(10.0, 30.0, 0.0), radius=1.2, height=6.0, name="tree2"),
    "cone": Obstacle(kind="cone", center=(-5.0, 4.0, 1.0), radius=2.0, height=8.0, name="tree3"),
    "sphere": Obstacle(kind="sphere", center=(1.0, 2.0, 6.0), radius=2.5, name="crown"),
    "pole": Obstacle(kind="cylinder", center=(50.0, 30.0, 0.0), radius=0.05, height=4.0, name="balloon2_pole"),
}


def fcl_object(o: Obstacle) -> fcl.CollisionObject:
    """FCL's cylinder and cone are centred on their axis' midpoint (the cone's apex at +height/2);
    ours stand on their base."""
    if o.kind == "box":
        return fcl.CollisionObject(fcl.Box(*o.size), fcl.Transform(np.array(o.center)))
    if o.kind == "sphere":
        return fcl.CollisionObject(fcl.Sphere(o.radius), fcl.Transform(np.array(o.center)))
    solid = fcl.Cylinder(o.radius, o.height) if o.kind == "cylinder" else fcl.Cone(o.radius, o.height)
    return fcl.CollisionObject(solid, fcl.Transform(np.array(o.center) + (0.0, 0.0, o.height / 2)))


def fcl_distance(shape: fcl.CollisionObject, point: np.ndarray) -> float:
    body = fcl.CollisionObject(fcl.Sphere(BODY), fcl.Transform(point))
    return fcl.distance(body, shape, fcl.DistanceRequest(), fcl.DistanceResult())


def around(o: Obstacle, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random points in a box reaching 3 m beyond the shape on every side (many near its surface)."""
    cx, cy, cz = o.center
    if o.kind == "box":
        half = np.asarray(o.size) / 2
        low, high = np.asarray(o.center) - half, np.asarray(o.center) + half
    elif o.kind == "sphere":
        low, high = np.asarray(o.center) - o.radius, np.asarray(o.center) + o.radius
    else:
        low = np.array([cx - o.radius, cy - o.radius, cz])
        high = np.array([cx + o.radius, cy + o.radius, cz + o.height])
    return rng.uniform(low - 3.0, high + 3.0, (count, 3))


def cone_surface_distance(o: Obstacle, point: np.ndarray) -> float:
    """Independently of the (r, z) reduction: the nearest of a sampling of the cone's slant and base in
    3-D (azimuth every 0.5°, 2,001 steps from rim to apex or centre), refined by Nelder-Mead."""
    cx, cy, cz = o.center

    def slant(angle, share):
        return np.stack(np.broadcast_arrays(cx + o.radius * (1 - share) * np.cos(angle),
                                            cy + o.radius * (1 - share) * np.sin(angle), cz + o.height * share), -1)

    def base(angle, share):
        return np.stack(np.broadcast_arrays(cx + o.radius * share * np.cos(angle),
                                            cy + o.radius * share * np.sin(angle), cz + 0 * share), -1)

    angles, shares = np.linspace(0.0, 2 * np.pi, 721)[:, None], np.linspace(0.0, 1.0, 2001)[None, :]
    best = math.inf
    for surface in (slant, base):
        gaps = np.linalg.norm(surface(angles, shares) - point, axis=-1)
        i, j = np.unravel_index(np.argmin(gaps), gaps.shape)

        def gap(x, surface=surface):
            return float(np.linalg.norm(surface(x[0], np.clip(x[1], 0.0, 1.0)) - point))

        refined = minimize(gap, [angles[i, 0], shares[0, j]], method="Nelder-Mead",
                           options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 2000})
        best = min(best, gaps[i, j], refined.fun)
    return best


@pytest.mark.parametrize("kind", sorted(SHAPES))
def test_every_primitive_agrees_with_fcl_outside_it(kind):
    o = SHAPES[kind]
    world = contact.shapes([o])
    rng = np.random.default_rng(len(kind))
    points = around(o, 4000, rng)
    ours = contact.signed_distance(points, world)[:, 0]
    outside = points[ours > BODY + 1e-3]  # FCL says -1 for a body that touches: no distance to compare
    assert len(outside) > 1500, len(outside)
    oracle = np.array([fcl_distance(fcl_object(o), p) for p in outside])
    gap = oracle - (contact.signed_distance(outside, world)[:, 0] - BODY)
    print(f"{kind}: {len(outside)} points outside, FCL - ours in [{gap.min():.1e}, {gap.max():.1e}] m")
    if o.kind == "cone":
        # FCL has closed forms for a sphere against a box, a cylinder or a sphere, but meets a cone by
        # GJK, which stops short of the minimum: up to 1.6 mm above it here, never below. Where FCL
        # and we differ most, a search of the surface in 3-D says which is right.
        assert -1e-9 < gap.min() and gap.max() < 2e-3
        worst = outside[np.argmax(gap)]
        sampled = cone_surface_distance(o, worst) - BODY
        ours_there = contact.signed_distance(worst, world)[0] - BODY
        assert abs(sampled - ours_there) < 1e-5 < abs(sampled - oracle.max())
    else:
        assert np.abs(gap).max() < 1e-9
    # and FCL sees contact wherever we are within the body's radius
    touching = points[ours < BODY - 1e-3][:200]
    assert len(touching) >= 20 and all(fcl_distance(fcl_object(o), p) <= 0 for p in touching)


@pytest.mark.parametrize("kind", sorted(SHAPES))
def test_every_primitive_agrees_with_fcls_signed_distance_in_contact(kind):
    """A body that touches: FCL's penetration depth (EPA) is our signed distance less the radius,
    centres inside the shape included."""
    o = SHAPES[kind]
    world = contact.shapes([o])
    # inside every kind, off the axis (FCL's EPA does not come back from a sphere centred on a cylinder's)
    middle = np.asarray(o.center) + (0.01, 0.007, o.height / 3)
    points = around(o, 4000, np.random.default_rng(7))
    points = np.vstack([points[contact.signed_distance(points, world)[:, 0] < BODY - 1e-3][:300], middle])
    ours = contact.signed_distance(points, world)[:, 0] - BODY
    assert len(points) > 20 and ours[-1] < -BODY  # the middle: the centre inside
    signed = fcl.DistanceRequest(enable_signed_distance=True)
    oracle = np.array([fcl.distance(fcl.CollisionObject(fcl.Sphere(BODY), fcl.Transform(p)), fcl_object(o), signed,
                                    fcl.DistanceResult()) for p in points])
    assert np.abs(oracle - ours).max() < 2e-6


def test_hand_cases_inside_and_on_the_surface():
    world = contact.shapes(SHAPES.values())
    assert world.names == ("building", "tree2", "tree3", "crown", "balloon2_pole")
    cases = [  # point, shape index, signed distance
        ((3.0, -2.0, 4.0), 0, -3.0),  # the box's centre: 3 m from the nearest faces (z)
        ((8.0, -2.0, 4.0), 0, 0.0),  # on its +x face
        ((9.0, 3.0, 4.0), 0, math.hypot(1.0, 1.0)),  # beyond an edge
        ((10.0, 30.0, 3.0), 1, -1.2),  # on the tree's axis, mid-height: the bark is nearest
        ((10.0, 30.0, 0.5), 1, -0.5),  # near its foot: the base is nearest
        ((10.0, 31.2, 2.0), 1, 0.0),  # on the bark
        ((10.0, 30.0, 7.0), 1, 1.0),  # above its top
        ((-5.0, 4.0, 1.5), 2, -0.5),  # the cone's axis just above the base
        ((-5.0, 4.0, 9.0), 2, 0.0),  # its apex
        ((-5.0, 4.0, 10.0), 2, 1.0),  # above the apex
        ((-3.0, 4.0, 1.0), 2, 0.0),  # the rim of its base
        ((-5.0 + 1.0, 4.0, 5.0), 2, 0.0),  # on the slant: r = R (1 - w / H) at w = 4
        ((-5.0, 4.0, 0.0), 2, 1.0),  # below the base's centre
        ((1.0, 2.0, 6.0), 3, -2.5),  # the sphere's centre
        ((1.0, 2.0, 8.5), 3, 0.0),  # its top
        ((50.3, 30.0, 2.0), 4, 0.25),  # 0.3 m from the pole's axis
        ((50.0, 30.0, 4.3), 4, 0.3),  # 0.3 m above its top
    ]
    points = np.array([p for p, _, _ in cases])
    distances = contact.signed_distance(points, world)
    for (point, k, expected), row in zip(cases, distances):
        assert row[k] == pytest.approx(expected, abs=1e-9), (point, world.names[k], row[k])
    # a cone inside point off the axis: the slant is nearer than the base
    inside = contact.signed_distance(np.array([-5.0 + 1.5, 4.0, 2.0]), world)[2]
    slant = (1.5 * 8.0 + 1.0 * 2.0 - 2.0 * 8.0) / math.hypot(2.0, 8.0)  # (r H + w R - R H) / |(H, R)|
    assert inside == pytest.approx(slant) and inside < 0


def test_any_leading_shape_and_the_ground_is_not_a_solid():
    world = contact.shapes([Obstacle(kind="plane", center=(0.0, 0.0, 0.0), name="ground"), *SHAPES.values()])
    assert len(world) == 5 and "ground" not in world.names
    rng = np.random.default_rng(3)
    points = rng.uniform(-20.0, 60.0, (5, 3, 3))  # sub-steps × UAVs × xyz
    together = contact.signed_distance(points, world)
    assert together.shape == (5, 3, 5)
    one_by_one = np.array([[contact.signed_distance(p, world) for p in row] for row in points])
    assert np.array_equal(together, one_by_one)
    empty = contact.shapes([])
    assert contact.signed_distance(points, empty).shape == (5, 3, 0)


def test_an_unnamed_obstacle_is_called_by_its_kind_and_place():
    assert contact.label(Obstacle(kind="box", center=(-20.0, -20.25, 2.0))) == "unnamed box (-20.0, -20.2)"
    assert contact.label(SHAPES["pole"]) == "balloon2_pole"
