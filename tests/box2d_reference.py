"""pybox2d (Gymnasium's Box2D) reference roll-outs shared by the physics2d tests."""
import numpy as np


def box_trajectory(b2, edges, position, angle, half, velocity=(1.0, 0.0), steps=20, boxes=(), omega=0.0):
    """A density-1, friction-0.2 box of half-extents ``half`` at ``position``/``angle`` with ``velocity``
    and angular velocity ``omega``,
    over static friction-2.5 edge fixtures ``edges`` ((p0, p1) each) and box fixtures ``boxes``
    ((x0, x1, y0, y1) each), stepped at 50 Hz with 180 velocity and 60 position iterations (the
    walker's settings) -> (steps, 3): x, y, angle after each step."""
    world = b2.b2World(gravity=(0, -10))
    for e in edges:
        world.CreateStaticBody(fixtures=b2.b2FixtureDef(shape=b2.b2EdgeShape(vertices=list(e)), friction=2.5))
    for x0, x1, y0, y1 in boxes:
        world.CreateStaticBody(fixtures=b2.b2FixtureDef(
            shape=b2.b2PolygonShape(vertices=[(x0, y0), (x1, y0), (x1, y1), (x0, y1)]), friction=2.5))
    body = world.CreateDynamicBody(position=tuple(position), angle=angle, fixtures=b2.b2FixtureDef(
        shape=b2.b2PolygonShape(box=tuple(half)), density=1.0, friction=0.2))
    body.linearVelocity = tuple(velocity)
    body.angularVelocity = float(omega)
    out = []
    for _ in range(steps):
        world.Step(1 / 50, 180, 60)
        out.append([body.position[0], body.position[1], body.angle])
    return np.asarray(out)
