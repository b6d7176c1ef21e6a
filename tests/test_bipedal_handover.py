"""``envs.bipedal.parity.gym_state``: a Gymnasium walker's Box2D state handed into ours gives the same
observation, carries Box2D's warm-start impulses slot by slot, and one step later both engines still
agree: on the flat level (edge contacts, joints at their limits) and on Hardcore with a lower leg on
an obstacle (the box contacts' feature keys, which Box2D lists leg first)."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.bipedal import BipedalWalker, parity


@functools.lru_cache(maxsize=1)
def walker_and_step():
    """Both levels' cases share one walker and one compiled step (the time of impact off in both engines:
    a third of the compile)."""
    walker = BipedalWalker(continuous=False)
    return walker, jax.jit(walker.step_without_reset)


def box2d_impulses(u, bodies):
    """Box2D's accumulated normal impulses of ``bodies``' touching contact points, sorted."""
    return np.sort([p.normalImpulse for b in bodies for ce in b.contacts if ce.contact.touching
                    for p in ce.contact.manifold.points[: ce.contact.manifold.pointCount]])


def on_a_box(u, leg):
    for ce in u.legs[leg].contacts:
        c = ce.contact
        other = c.fixtureB if c.fixtureA.body == u.legs[leg] else c.fixtureA
        if c.touching and type(other.shape).__name__ == "b2PolygonShape":
            return True
    return False


def handed_over(gym_id, seed, until):
    """Gymnasium's gait from ``seed`` until ``until(unwrapped env, step)``; the env, its last observation,
    the next action, our state for it."""
    gym = pytest.importorskip("gymnasium")
    from gymnasium.envs.box2d.bipedal_walker import BipedalWalkerHeuristics

    env = gym.make(gym_id)
    u = env.unwrapped
    u.world.continuousPhysics = False
    s, _ = env.reset(seed=seed)
    h, a = BipedalWalkerHeuristics(), np.zeros(4)
    for t in range(1, 600):
        prev = parity.gym_bodies(u)["angle"]
        s, *_ = env.step(a)
        a = h.step_heuristic(s)
        if until(u, t):
            break
    else:
        raise AssertionError(f"{gym_id} seed {seed}: the case never came")
    walker, _ = walker_and_step()
    return env, s, a, parity.gym_state(u, walker, prev_angle=prev, time=t)


def check(env, s, a, state, atol_next, lidar_atol):
    """``lidar_atol``: our lidar reads the rasterised terrain profile, exact on grass; near an obstacle's
    faces it is a few hundredths off Box2D's ray casts (99th percentile 0.036 along the stump
    hand-over's runs, docs/bipedal.md)."""
    walker, step = walker_and_step()
    u = env.unwrapped
    obs = np.asarray(walker.observation(state.world, state.leg_contact, state.profile))
    np.testing.assert_allclose(obs[:14], s[:14], atol=1e-4)  # hull, joints, legs' contacts
    np.testing.assert_allclose(obs[14:], s[14:], atol=lidar_atol)
    # Box2D's accumulated impulses in our slots, point by point (the non-zero ones: a point either engine
    # keeps without an impulse carries nothing into the next step; Box2D's hull touches nothing here)
    b2 = box2d_impulses(u, u.legs)
    ours = np.sort(np.asarray(state.world.normal_impulse)[np.asarray(state.world.touching)])
    assert b2.sum() > 0.1
    np.testing.assert_allclose(ours[ours > 0], b2[b2 > 0], rtol=1e-4, atol=1e-6)
    assert float(jnp.abs(state.world.joint_impulse).sum()) > 0.1
    # one step of each engine from there, the same action
    params = walker.default_params.replace(max_steps=jnp.int32(1600))
    obs1, *_ = step(jax.random.PRNGKey(0), state, jnp.asarray(a, jnp.float32), params)
    s1, *_ = env.step(a)
    np.testing.assert_allclose(np.asarray(obs1)[:14], s1[:14], atol=atol_next)
    np.testing.assert_allclose(np.asarray(obs1)[14:], s1[14:], atol=max(atol_next, lidar_atol))
    env.close()


def test_gym_state_gives_gymnasiums_observation_and_step():
    # into the gait: feet on the ground, joints driven, some at a limit
    check(*handed_over("BipedalWalker-v3", 3, lambda u, t: t == 70), atol_next=2e-3, lidar_atol=1e-4)


def test_gym_state_hands_over_a_leg_on_an_obstacle():
    # Hardcore, the first step a lower leg touches an obstacle's polygon (seed 3: the right leg at step 105)
    env, s, a, state = handed_over("BipedalWalkerHardcore-v3", 3, lambda u, t: on_a_box(u, 1) or on_a_box(u, 3))
    assert bool(np.asarray(state.leg_box_pairs).any())  # the leg's box pair, as Box2D's contact
    check(env, s, a, state, atol_next=2e-3, lidar_atol=0.05)  # 0.012 here, 0.036 a step later
