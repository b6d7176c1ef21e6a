"""pybox2d (Gymnasium's Box2D) reference roll-outs of a lone box, shared by the physics2d tests and
experiments/bipedal_shin_stump.py. pybox2d comes with the test extra only: callers pass its module
(``load_box2d()`` or ``pytest.importorskip("Box2D")``)."""
import numpy as np


def load_box2d():
    """pybox2d's module; an ImportError of one line naming the extra that installs it when it is missing."""
    try:
        import Box2D
    except ImportError as err:
        raise ImportError("pybox2d is not installed (it comes with the test extra: pip install -e '.[test]')") from err
    return Box2D


def box_world(b2, edges, position, angle, half, velocity=(1.0, 0.0), boxes=(), omega=0.0, continuous=True):
    """(world, body): a density-1, friction-0.2 box of half-extents ``half`` at ``position``/``angle`` with
    ``velocity`` and angular velocity ``omega``, over static friction-2.5 edge fixtures ``edges``
    ((p0, p1) each) and box fixtures ``boxes`` ((x0, x1, y0, y1) each), gravity -10, Box2D's
    ``continuousPhysics`` set to ``continuous``."""
    world = b2.b2World(gravity=(0, -10))
    world.continuousPhysics = continuous
    for e in edges:
        world.CreateStaticBody(fixtures=b2.b2FixtureDef(shape=b2.b2EdgeShape(vertices=list(e)), friction=2.5))
    for x0, x1, y0, y1 in boxes:
        world.CreateStaticBody(fixtures=b2.b2FixtureDef(
            shape=b2.b2PolygonShape(vertices=[(x0, y0), (x1, y0), (x1, y1), (x0, y1)]), friction=2.5))
    body = world.CreateDynamicBody(position=tuple(position), angle=angle, fixtures=b2.b2FixtureDef(
        shape=b2.b2PolygonShape(box=tuple(half)), density=1.0, friction=0.2))
    body.linearVelocity = tuple(velocity)
    body.angularVelocity = float(omega)
    return world, body


def step(world) -> None:
    """One step at 50 Hz with 180 velocity and 60 position iterations (the walker's settings)."""
    world.Step(1 / 50, 180, 60)


def box_pose(body) -> list:
    """[x, y, angle] of the body's origin."""
    return [body.position[0], body.position[1], body.angle]


def box_trajectory(b2, edges, position, angle, half, velocity=(1.0, 0.0), steps=20, boxes=(), omega=0.0,
                   continuous=True):
    """``box_world``'s box stepped ``steps`` times (``step``) -> (steps, 3): x, y, angle after each step."""
    world, body = box_world(b2, edges, position, angle, half, velocity, boxes, omega, continuous)
    out = []
    for _ in range(steps):
        step(world)
        out.append(box_pose(body))
    return np.asarray(out)
