"""``envs.bipedal.parity.gym_state``: a Gymnasium walker's Box2D state handed into ours gives the same
observation, carries Box2D's warm-start impulses, and one step later both engines still agree."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.bipedal import BipedalWalker, parity


def test_gym_state_gives_gymnasiums_observation_and_step():
    gym = pytest.importorskip("gymnasium")
    from gymnasium.envs.box2d.bipedal_walker import BipedalWalkerHeuristics

    env = gym.make("BipedalWalker-v3")
    u = env.unwrapped
    u.world.continuousPhysics = False  # both engines without the time of impact: a third of the compile
    s, _ = env.reset(seed=3)
    h, a = BipedalWalkerHeuristics(), np.zeros(4)
    for _ in range(70):  # into the gait: feet on the ground, joints driven, some at a limit
        prev = parity.gym_bodies(u)["angle"]
        s, *_ = env.step(a)
        a = h.step_heuristic(s)
    walker = BipedalWalker(continuous=False)
    state = parity.gym_state(u, walker, prev_angle=prev, time=70)
    obs = walker.observation(state.world, state.leg_contact, state.profile)
    np.testing.assert_allclose(np.asarray(obs), s, atol=1e-4)
    # Box2D's accumulated impulses, in our slots: the joints' and the legs' touching contacts'
    box2d_normal = sum(p.normalImpulse for b in u.legs for ce in b.contacts if ce.contact.touching
                       for p in ce.contact.manifold.points[: ce.contact.manifold.pointCount])
    assert box2d_normal > 0.1
    np.testing.assert_allclose(float(jnp.sum(state.world.normal_impulse)), box2d_normal, rtol=1e-4)
    assert float(jnp.abs(state.world.joint_impulse).sum()) > 0.1
    # one step of each engine from there, the same action
    params = walker.default_params.replace(max_steps=jnp.int32(1600))
    obs1, *_ = jax.jit(walker.step_without_reset)(jax.random.PRNGKey(0), state, jnp.asarray(a, jnp.float32), params)
    s1, *_ = env.step(a)
    np.testing.assert_allclose(np.asarray(obs1), s1, atol=2e-3)
    env.close()
