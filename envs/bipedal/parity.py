"""Parity harness: one controller in our walker (vmapped) and in Gymnasium's Box2D BipedalWalker, per
setting: return distribution, episode length, fall rate. The controller is Gymnasium's scripted gait
(``BipedalWalkerHeuristics``), or with ``--policy`` the PPO students that ``python -m shed_jax ppo
--env bipedal`` saved (``policy.msgpack``, deterministic actions, ``--episodes`` per seed):

    python -m envs.bipedal.parity --episodes 200 --out docs/results/bipedal.json
    python -m envs.bipedal.parity --episodes 50 --settings flat --jax-only
    python -m envs.bipedal.parity --policy runs/ppo_bipedal/policy.msgpack --episodes 25 \
        --out docs/results/bipedal.json          # adds the rows "policy_<setting>", keeps the others
    # the reverse check: a policy trained in Box2D (experiments/bipedal_box2d_ppo.py), rows "box2d_policy_<setting>"
    python -m envs.bipedal.parity --policy runs/box2d_ppo/policy.msgpack --tag box2d_policy --settings flat ...

The gait plays each episode as Gymnasium's own demo loop does: the first action is zero, every later
one is the heuristic's answer to the last observation; a policy answers every observation, the reset
one included. An episode ends on termination or the
level's time limit (1600 steps flat, 2000 Hardcore, as Gymnasium registers them). A fall is a
termination with reward -100 (hull contact or x < 0). Bar (docs/bipedal.md "Parity"): mean return
within 15 % of Gymnasium's or within 2 standard errors of the difference, whichever is wider, and
fall rate within 0.1. Each row also counts the falls by the obstacle nearest to where the hull was
(``*_fall_sites``: stump, stairs, pit, or grass when none is within 3 terrain steps), and the same for
the episodes that reached the time limit without falling (``*_limit_sites``: where the walker stood).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import re
import time

import jax
import jax.numpy as jnp
import numpy as np

from envs.bipedal.env import BipedalOptions, BipedalWalker
from envs.bipedal.heuristic import heuristic, heuristic_init
from envs.walker import constants as C
from envs.walker.levels import LEVELS
from shed_jax.runtime import provenance

# setting -> (named level, Gymnasium id)
SETTINGS = {
    "flat": ("BipedalWalker", "BipedalWalker-v3"),
    "hardcore": ("Hardcore", "BipedalWalkerHardcore-v3"),
}


def summarize(returns, lengths, falls) -> dict:
    """Return statistics, fall rate, mean length, and the mean length of the episodes that fell and
    of the others (None where there are none): a mean length mixes the two."""
    r = np.asarray(returns, np.float64)
    n, f = np.asarray(lengths, np.float64), np.asarray(falls, bool)
    part = lambda m: float(n[m].mean()) if m.any() else None  # noqa: E731
    return dict(episodes=int(r.size), mean=float(r.mean()), std=float(r.std()), se=float(r.std() / np.sqrt(r.size)),
                fall=float(np.mean(falls)), length=float(np.mean(lengths)), length_fell=part(f), length_other=part(~f),
                quartiles=[float(q) for q in np.percentile(r, [25, 50, 75])])


def heuristic_controller():
    """Gymnasium's gait as ``(first(theta, obs) -> (action, carry), next(theta, carry, obs) -> (action,
    carry))``, ``theta`` unused: the first action is zero, as in Gymnasium's demo loop."""
    return (lambda theta, obs: (jnp.zeros(4, jnp.float32), heuristic_init())), (lambda theta, h, obs: heuristic(h, obs))


def policy_controller(student):
    """A saved student's deterministic policy in the form of ``heuristic_controller``; ``theta`` is
    one seed of ``load_policy`` (an argument of the compiled program, so one compile serves every
    seed) and the carry is unused."""
    def act(theta, obs):
        return student.act(theta, jax.random.PRNGKey(0), obs, deterministic=True)

    return (lambda theta, obs: (act(theta, obs), jnp.int32(0))), (lambda theta, c, obs: (act(theta, obs), c))


def jax_episodes(level: str, episodes: int, seed: int = 0, chunk: int = 100, controller=None, thetas=(None,),
                 max_steps: int | None = None, **env_options) -> list[dict]:
    """First episode of ``controller`` (default: the heuristic) on ``episodes`` fresh terrains of the
    named level, once per entry of ``thetas`` (the controller's parameters; entry i uses root seed
    ``seed + 1000 i``), from one compiled program: a list of dicts of numpy arrays. ``max_steps``
    shortens the level's time limit (tests)."""
    env = BipedalWalker(**env_options)
    params = LEVELS[level]()
    if max_steps is not None:
        params = params.replace(max_steps=jnp.asarray(max_steps, jnp.asarray(params.max_steps).dtype))
    max_steps = int(params.max_steps)
    first, next_ = heuristic_controller() if controller is None else controller

    def one(key, theta):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)
        terrain = state.terrain  # the episode's, for where it ended

        def body(carry, k):
            obs, state, h, a, done_before, out = carry
            obs, state, reward, done, info = env.step_without_reset(k, state, a, params)
            a, h = next_(theta, h, obs)
            first = done & ~done_before
            fell = info["terminated"] & (reward == -100.0)
            out = jax.tree_util.tree_map(lambda o, n: jnp.where(first, n, o), out, dict(
                ret=info["episode_return"], length=info["episode_length"], fall=fell, x=info["x"]))
            return (obs, state, h, a, done_before | done, out), None

        out0 = dict(ret=jnp.float32(0), length=jnp.int32(0), fall=jnp.bool_(False), x=jnp.float32(0))
        a, h = first(theta, obs)
        carry = (obs, state, h, a, jnp.bool_(False), out0)
        (_, _, _, _, _, out), _ = jax.lax.scan(body, carry, jax.random.split(k1, max_steps))
        return dict(out, kinds=terrain.kinds, column_x=terrain.x)

    run = jax.jit(jax.vmap(one, in_axes=(0, None)))
    results = []
    for j, theta in enumerate(thetas):
        keys = jax.random.split(jax.random.PRNGKey(seed + 1000 * j), episodes)
        outs = []
        for i in range(0, episodes, chunk):
            part = keys[i:i + chunk]
            if part.shape[0] < chunk:  # same compiled shape for the last chunk
                part = jnp.concatenate([part, keys[: chunk - part.shape[0]]])
            outs.append(jax.tree_util.tree_map(np.asarray, run(part, theta)))
        res = {k: np.concatenate([o[k] for o in outs])[:episodes] for k in outs[0]}
        kinds, cx = res.pop("kinds"), res.pop("column_x")
        res["obstacles"] = [column_obstacles(k, x) for k, x in zip(kinds, cx)]
        results.append(res)
    return results


OBSTACLE_KINDS = {C.STUMP: "stump", C.STAIRS: "stairs", C.PIT: "pit"}


def column_obstacles(kinds, column_x) -> list[tuple[float, float, str]]:
    """Our terrain's obstacles as (x0, x1, kind): each run of columns of one non-grass state."""
    out, start = [], None
    for i, k in enumerate(list(kinds) + [C.GRASS]):
        if start is not None and k != kinds[start]:
            out.append((float(column_x[start]), float(column_x[i - 1]) + C.TERRAIN_STEP, OBSTACLE_KINDS[int(kinds[start])]))
            start = None
        if start is None and k != C.GRASS and i < len(kinds):
            start = i
    return out


def gym_obstacles(env) -> list[tuple[float, float, str]]:
    """A Gymnasium walker's obstacles after its reset, as (x0, x1, kind), from its polygon fixtures:
    a box taller than 3 steps is a pit wall (4 steps tall; a pit's two walls are one obstacle, from the
    first wall's x0 to the second's x1, as our pit columns), a box wider than 3 steps a stair step (4
    wide), any other a stump (1 or 2 steps square)."""
    out = []
    for body in env.terrain:
        shape = body.fixtures[0].shape
        if type(shape).__name__ != "b2PolygonShape":
            continue
        v = np.asarray(shape.vertices)
        x0, x1 = float(v[:, 0].min()), float(v[:, 0].max())
        tall = v[:, 1].max() - v[:, 1].min() > 3 * C.TERRAIN_STEP
        out.append((x0, x1, "pit" if tall else ("stairs" if x1 - x0 > 3 * C.TERRAIN_STEP else "stump")))
    out.sort()
    merged = []
    for ob in out:  # Gymnasium creates a pit's walls in pairs, the second 3 or 4 steps after the first
        if ob[2] == "pit" and merged and merged[-1][2] == "pit" and merged[-1][3] == 1:
            merged[-1] = (merged[-1][0], ob[1], "pit", 2)
        else:
            merged.append(ob + (1,))
    return [ob[:3] for ob in merged]


def end_sites(x, mask, obstacles, reach: float = 3 * C.TERRAIN_STEP) -> dict:
    """The episodes where ``mask`` holds counted by the kind of obstacle nearest to the hull's x at their
    end (``grass`` when none is within ``reach``): per episode its end x, mask flag and obstacle list
    (x0, x1, kind). With ``mask`` the fall flags these are the fall sites; with "reached the time limit
    without falling", where the walker stood (or was stuck) when time ran out."""
    counts = {"stump": 0, "stairs": 0, "pit": 0, "grass": 0}
    for xe, f, obs in zip(x, mask, obstacles):
        if not f:
            continue
        dist = [max(a - xe, xe - b, 0.0) for a, b, _ in obs]
        j = int(np.argmin(dist)) if dist else -1
        counts[obs[j][2] if j >= 0 and dist[j] <= reach else "grass"] += 1
    return counts


def site_fields(side: str, d: dict, limit: int) -> dict:
    """A side's ``*_fall_sites`` and ``*_limit_sites`` (the episodes that reached ``limit`` steps without
    falling) from its episodes ``d`` (``x``, ``fall``, ``length``, ``obstacles``)."""
    fall = np.asarray(d["fall"], bool)
    at_limit = ~fall & (np.asarray(d["length"]) >= limit)
    return {f"{side}_fall_sites": end_sites(d["x"], fall, d["obstacles"]),
            f"{side}_limit_sites": end_sites(d["x"], at_limit, d["obstacles"])}


def _as_chain(walker_cls):
    """``walker_cls._generate_terrain`` with the separate grass edges replaced by one Box2D chain (a
    diagnostic: a chain's ghost vertices remove the contacts Box2D makes at the edges' junctions)."""
    from Box2D.b2 import chainShape, edgeShape, fixtureDef

    original = walker_cls._generate_terrain

    def generate(self, hardcore):
        original(self, hardcore)
        edges = [t for t in self.terrain if isinstance(t.fixtures[0].shape, edgeShape)]
        for t in edges:
            self.world.DestroyBody(t)
        chain = self.world.CreateStaticBody(fixtures=fixtureDef(
            shape=chainShape(vertices=list(zip(self.terrain_x, self.terrain_y))), friction=2.5))
        chain.color1 = chain.color2 = (76, 255, 76)
        self.terrain = [t for t in self.terrain if t not in edges] + [chain]

    return generate


def gym_episodes(gym_id: str, episodes: int, seed: int = 0, chain: bool = False, policy=None,
                 max_steps: int | None = None, continuous: bool = True) -> dict:
    """Gymnasium's own env and gait, or ``policy`` (observation -> action, numpy) instead of the
    gait; ``chain``: its grass as one chain shape (see ``_as_chain``); ``max_steps``: a shorter limit;
    ``continuous=False``: Box2D's time of impact off (``world.continuousPhysics``)."""
    import gymnasium as gym
    from gymnasium.envs.box2d.bipedal_walker import BipedalWalker as GymWalker
    from gymnasium.envs.box2d.bipedal_walker import BipedalWalkerHeuristics

    env = gym.make(gym_id, **({} if max_steps is None else {"max_episode_steps": max_steps}))
    if chain:
        env.unwrapped._generate_terrain = _as_chain(GymWalker).__get__(env.unwrapped)
    env.unwrapped.world.continuousPhysics = continuous
    rets, lens, falls, xs, obstacles = [], [], [], [], []
    for ep in range(episodes):
        s, _ = env.reset(seed=seed + ep)
        obstacles.append(gym_obstacles(env.unwrapped))
        h = BipedalWalkerHeuristics()
        a = np.zeros(4) if policy is None else policy(s)
        total, n = 0.0, 0
        while True:
            s, r, term, trunc, _ = env.step(a)
            total += r
            n += 1
            a = h.step_heuristic(s) if policy is None else policy(s)
            if term or trunc:
                break
        rets.append(total)
        lens.append(n)
        falls.append(bool(term and r == -100))
        xs.append(float(env.unwrapped.hull.position.x))
    env.close()
    return dict(ret=np.asarray(rets), length=np.asarray(lens), fall=np.asarray(falls), x=np.asarray(xs),
                obstacles=obstacles)


# ------------------------------------------------------------------ a Box2D state handed into ours
def gym_terrain(env, max_boxes: int = 64):
    """A Gymnasium walker's terrain after its reset (``env`` unwrapped) as our ``Terrain``: its 200
    polyline vertices and its polygon fixtures as boxes (x0, x1, y0, y1), sorted as our generator
    emits them (``rasterise`` searches them by x0). ``kinds`` marks the columns under each box by the
    box's kind (``gym_obstacles``), for ``column_obstacles``."""
    from envs.walker import terrain as T

    boxes = []
    for body in env.terrain:
        shape = body.fixtures[0].shape
        if type(shape).__name__ == "b2PolygonShape":
            v = np.asarray(shape.vertices, np.float64)
            boxes.append((v[:, 0].min(), v[:, 0].max(), v[:, 1].min(), v[:, 1].max()))
    boxes.sort(key=lambda b: (b[0], b[2]))
    if len(boxes) > max_boxes:
        raise ValueError(f"{len(boxes)} obstacle boxes, more than max_boxes={max_boxes}")
    x = np.asarray(env.terrain_x, np.float64)
    kinds = np.full(x.shape, C.GRASS, np.int32)
    code = {v: k for k, v in OBSTACLE_KINDS.items()}
    for x0, x1, kind in gym_obstacles(env):
        kinds[(x >= x0 - 1e-4) & (x < x1 - 1e-4)] = code[kind]
    b = np.zeros((max_boxes, 4), np.float32)
    if boxes:
        b[: len(boxes)] = boxes
    return T.Terrain(x=jnp.asarray(x, jnp.float32), y=jnp.asarray(env.terrain_y, jnp.float32), boxes=jnp.asarray(b),
                     box_valid=jnp.arange(max_boxes) < len(boxes), n_boxes=jnp.int32(len(boxes)),
                     kinds=jnp.asarray(kinds))


def gym_bodies(env) -> dict:
    """The walker's Box2D state in our body order (hull, upper and lower leg -1, upper and lower leg +1):
    centre of mass (5, 2), angle (5,), velocity of the centre of mass (5, 2), spin (5,), float64."""
    bodies = [env.hull] + list(env.legs)  # Gymnasium's legs: upper -1, lower -1, upper +1, lower +1
    return dict(com=np.array([tuple(b.worldCenter) for b in bodies]), angle=np.array([b.angle for b in bodies]),
                vel=np.array([tuple(b.linearVelocity) for b in bodies]),
                omega=np.array([b.angularVelocity for b in bodies]))


def gym_state(env, walker: BipedalWalker, terrain=None, prev_angle=None, time: int = 0, episode_return: float = 0.0):
    """Our ``BipedalState`` for a Gymnasium walker's current Box2D state (``env`` unwrapped, between two
    steps), so that both engines can go on from the same physical state.

    Handed over: every body's centre of mass, angle, velocity and spin; Box2D's accumulated joint
    impulses (point, limit and motor: ``GetReactionForce`` etc. times the step) and contact impulses
    (per fixture and ``b2ContactID`` key, on our manifolds at that pose), which warm start the next
    step in both engines; the contact flags (Gymnasium's ``ground_contact``, per lower leg and edge or
    box Box2D's ``IsTouching``); Gymnasium's ``prev_shaping``. A joint's limit state is the one Box2D
    computed at the start of the last step: pass the bodies' angles then as ``prev_angle`` (5,), or the
    current pose's is used (it differs only where a joint crossed its limit in that step). ``terrain``:
    ``gym_terrain(env)`` (built when None). Not handed over: Box2D's sleep timers (the walker does not
    sleep while it moves) and its cached time-of-impact state (reset at every step)."""
    from envs import physics2d
    from envs.bipedal import model as M
    from envs.physics2d import joint as jnt
    from envs.physics2d.world import edge_constraints, fixture_keys
    from envs.walker import terrain as T

    model, o = walker.model, walker.options
    if terrain is None:
        terrain = gym_terrain(env, o.max_boxes)
    g = gym_bodies(env)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    bodies = physics2d.BodyState(com=f32(g["com"]), angle=f32(g["angle"]), vel=f32(g["vel"]), omega=f32(g["omega"]))
    world = physics2d.init_world(model, bodies)
    inv_dt = 1.0 / model.config.dt
    angle = np.asarray(g["angle"] if prev_angle is None else prev_angle, np.float64)
    jimp, jmot, jstate = [], [], []
    for k, J in enumerate(model.joints):
        bj = env.joints[M.GYM_JOINT[k]]
        f = bj.GetReactionForce(inv_dt)
        jimp.append((f[0] / inv_dt, f[1] / inv_dt, bj.GetReactionTorque(inv_dt) / inv_dt))
        jmot.append(bj.GetMotorTorque(inv_dt) / inv_dt)
        q = angle[J.body_b] - angle[J.body_a] - J.reference_angle
        jstate.append(jnt.AT_LOWER if q <= J.lower else (jnt.AT_UPPER if q >= J.upper else jnt.INACTIVE))
    profile = T.rasterise(terrain, walker.grid)
    hull_x = float(physics2d.body_origin(model, bodies)[M.HULL, 0])
    ground, col = walker.ground_window(profile, jnp.float32(hull_x))
    edges, valid, boxes, box_ok, box_index = walker.fixture_window(terrain, ground, col)
    ec = edge_constraints(model, bodies, edges, valid, boxes, box_ok)
    on, key = np.asarray(ec["on"]), np.asarray(ec["key"])
    # Box2D's touching contacts of each leg: fixture key (ours: the edge's or box's x0) -> {feature key: impulses}
    gym_bodies_ = [env.hull] + list(env.legs)
    b2 = {}
    xs, ys = np.asarray(env.terrain_x), np.asarray(env.terrain_y)
    n_box = int(terrain.n_boxes)
    tboxes = np.asarray(terrain.boxes)[:n_box]
    leg_pairs = np.zeros((2, o.window_columns), bool)
    leg_box_pairs = np.zeros((2, o.max_boxes), bool)
    for i, body in enumerate(gym_bodies_):
        for ce in body.contacts:
            c = ce.contact
            if not c.touching:
                continue
            leg_is_a = c.fixtureA.body == body  # Box2D orders two polygons by broad-phase proxy, ours the obstacle first
            shape = (c.fixtureB if leg_is_a else c.fixtureA).shape
            v = np.asarray(shape.vertices, np.float64)
            x0 = np.float32(v[:, 0].min())
            is_box = type(shape).__name__ == "b2PolygonShape"
            fkey = int(fixture_keys(x0, box=is_box))
            swap = lambda k: ((k >> 8) & 255) | ((k & 255) << 8) | (((k >> 24) & 255) << 16) | (((k >> 16) & 255) << 24)  # noqa: E731
            pts = {(swap(int(p.id.key)) if leg_is_a else int(p.id.key)): (p.normalImpulse, p.tangentImpulse)
                   for p in c.manifold.points[: c.manifold.pointCount]}
            b2.setdefault(i, {}).setdefault(fkey, {}).update(pts)
            if i in M.LOWER:
                side = M.LOWER.index(i)
                if is_box:
                    j = int(np.argmin(np.abs(tboxes[:, 0] - v[:, 0].min()) + np.abs(tboxes[:, 2] - v[:, 1].min())))
                    leg_box_pairs[side, j] = True
                else:
                    j = int(np.argmin(np.abs(xs - v[0, 0]) + np.abs(ys - v[0, 1])))  # the edge's column
                    if 0 <= j - int(col) < o.window_columns:
                        leg_pairs[side, j - int(col)] = True
    ln = np.zeros(on.shape, np.float32)
    lt = np.zeros(on.shape, np.float32)
    for e, i in enumerate(ec["body"]):
        if on[e]:
            ln[e], lt[e] = b2.get(i, {}).get(int(key[e, 0]), {}).get(int(key[e, 1]), (0.0, 0.0))
    world = world.replace(normal_impulse=f32(ln), tangent_impulse=f32(lt), touching=jnp.asarray(on),
                          contact_key=jnp.asarray(np.where(on[:, None], key, 0), jnp.int32),
                          joint_impulse=f32(jimp), motor_impulse=f32(jmot), limit_state=jnp.asarray(jstate, jnp.int32))
    from envs.bipedal.env import BipedalState
    return BipedalState(time=jnp.int32(time), episode_return=jnp.float32(episode_return), world=world, profile=profile,
                        prev_shaping=jnp.float32(env.prev_shaping),
                        leg_contact=jnp.asarray([bool(env.legs[1].ground_contact), bool(env.legs[3].ground_contact)]),
                        leg_pairs=jnp.asarray(leg_pairs), window=col, terrain=terrain,
                        leg_box_pairs=jnp.asarray(leg_box_pairs))


def passes(gym: dict, ours: dict) -> bool:
    """The parity bar: |mean difference| <= max(15 % of |Gymnasium's mean|, 2 SE of the difference),
    and |fall-rate difference| <= 0.1."""
    se = np.sqrt(gym["se"] ** 2 + ours["se"] ** 2)
    tol = max(0.15 * abs(gym["mean"]), 2.0 * se)
    return bool(abs(ours["mean"] - gym["mean"]) <= tol and abs(ours["fall"] - gym["fall"]) <= 0.1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--settings", default="flat", help=f"comma-separated, from {', '.join(SETTINGS)}")
    p.add_argument("--chunk", type=int, default=100, help="our episodes per compiled batch")
    p.add_argument("--jax-only", action="store_true")
    p.add_argument("--gym-only", action="store_true")
    p.add_argument("--gym-chain", action="store_true",
                   help="diagnostic: Gymnasium's grass as one chain shape (no contacts at edge junctions)")
    p.add_argument("--iterations", default=None, metavar="V/P", help="our solver passes (default Box2D's 180/60)")
    p.add_argument("--terrain-resolution", type=int, default=None, metavar="R",
                   help="diagnostic: our terrain profile samples per terrain step (default 4): an obstacle's face "
                        "is 0.467/R m wide and its columns have a contact edge every 0.467/R m")
    p.add_argument("--no-toi", action="store_true",
                   help="diagnostic: the time of impact off on both sides (Box2D's continuousPhysics, ours continuous)")
    p.add_argument("--obstacles", default=None, choices=("polygon", "profile"),
                   help="diagnostic: what our legs touch at obstacles (BipedalOptions.obstacles; default polygon)")
    p.add_argument("--toi-events", type=int, default=None, metavar="K",
                   help="diagnostic: our time-of-impact events per leg and step (BipedalOptions.toi_events; default 1)")
    p.add_argument("--policy", default=None, metavar="FILE",
                   help="a policy.msgpack of 'python -m shed_jax ppo --env bipedal' instead of the gait; "
                        "--episodes per saved seed; the rows are named <tag>_<setting> and --out keeps the others")
    p.add_argument("--tag", default="policy", help="with --policy: the rows' name prefix (default policy), e.g. "
                                                    "box2d_policy for a policy trained in Box2D")
    p.add_argument("--out", default=None, help="write the JSON record here (e.g. docs/results/bipedal.json)")
    args = p.parse_args(argv)
    if args.policy is not None:
        if (args.gym_chain or args.iterations or args.terrain_resolution is not None or args.obstacles or args.no_toi
                or args.toi_events is not None):
            p.error("--policy runs with Gymnasium's edges, Box2D's 180/60 passes and our default terrain; "
                    "drop --gym-chain/--iterations/--terrain-resolution/--obstacles/--no-toi/--toi-events")
        if not pathlib.Path(args.policy).is_file():
            p.error(f"--policy {args.policy}: no such file")
    if not re.fullmatch(r"[a-z0-9_]+", args.tag):
        p.error(f"--tag must be lower-case letters, digits and _, got {args.tag!r}")
    names = [n.strip() for n in args.settings.split(",")]
    unknown = [n for n in names if n not in SETTINGS]
    if unknown:
        p.error(f"unknown setting(s) {unknown}; known: {list(SETTINGS)}")
    if args.episodes < 1 or args.chunk < 1:
        p.error("--episodes and --chunk must be >= 1")
    opts = {}
    if args.iterations:
        try:
            v, q = (int(x) for x in args.iterations.split("/"))
        except ValueError:
            p.error(f"--iterations must be V/P, e.g. 180/60; got {args.iterations!r}")
        opts = dict(velocity_iterations=v, position_iterations=q)
    if args.terrain_resolution is not None:
        opts["terrain_resolution"] = args.terrain_resolution
    if args.obstacles is not None:
        opts["obstacles"] = args.obstacles
    if args.no_toi:
        opts["continuous"] = False
    if args.toi_events is not None:
        opts["toi_events"] = args.toi_events
    try:
        BipedalOptions(**opts)
    except ValueError as err:
        p.error(str(err))
    record = {**provenance("envs.bipedal.parity", argv),
              "device": jax.devices()[0].device_kind if not args.gym_only else "cpu",
              "seed": args.seed, "gym_terrain": "chain" if args.gym_chain else "edges",
              "gym_continuous": not args.no_toi, "ours_options": opts, "parity": {}}
    if args.policy is not None:
        return policy_main(args, names, record)
    for name in names:
        level, gym_id = SETTINGS[name]
        limit = int(LEVELS[level]().max_steps)
        row = {"episodes": args.episodes}
        if not args.jax_only:
            t = time.time()
            d = gym_episodes(gym_id, args.episodes, args.seed, chain=args.gym_chain, continuous=not args.no_toi)
            g = summarize(d["ret"], d["length"], d["fall"])
            print(f"gym  {name}: {time.time() - t:.0f}s mean {g['mean']:.1f} se {g['se']:.1f} fall {g['fall']:.2f} "
                  f"len {g['length']:.0f}", flush=True)
            row.update(gym_mean=g["mean"], gym_se=g["se"], gym_std=g["std"], gym_fall=g["fall"], gym_length=g["length"],
                       gym_length_fell=g["length_fell"], gym_length_other=g["length_other"],
                       gym_quartiles=g["quartiles"], **site_fields("gym", d, limit))
        if not args.gym_only:
            t = time.time()
            d = jax_episodes(level, args.episodes, args.seed, min(args.chunk, args.episodes), **opts)[0]
            o = summarize(d["ret"], d["length"], d["fall"])
            print(f"ours {name}: {time.time() - t:.0f}s mean {o['mean']:.1f} se {o['se']:.1f} fall {o['fall']:.2f} "
                  f"len {o['length']:.0f}", flush=True)
            row.update(ours_mean=o["mean"], ours_se=o["se"], ours_std=o["std"], ours_fall=o["fall"],
                       ours_length=o["length"], ours_length_fell=o["length_fell"], ours_length_other=o["length_other"],
                       ours_quartiles=o["quartiles"], **site_fields("ours", d, limit))
        if "gym_mean" in row and "ours_mean" in row:
            row["pass"] = passes(dict(mean=row["gym_mean"], se=row["gym_se"], fall=row["gym_fall"]),
                                 dict(mean=row["ours_mean"], se=row["ours_se"], fall=row["ours_fall"]))
            print(f"{name}: parity {'PASS' if row['pass'] else 'FAIL'}", flush=True)
        row.update({k: record[k] for k in PROVENANCE})
        record["parity"][name] = row
    if args.out:  # the gait's run is the record's header; other rows and keys (policy, speed) stay
        write_record(args.out, {k: v for k, v in record.items() if k != "parity"}, record["parity"], header=True)
    return 0


#: the fields that say where, how and when a row was measured
PROVENANCE = ("device", "date", "command")


def write_record(path, head: dict, rows: dict, header: bool) -> None:
    """Add ``rows`` to the record at ``path`` (``parity``), keeping its other rows and keys; ``head``
    becomes its header when ``header`` is set or the file is new."""
    out = pathlib.Path(path)
    rec = json.loads(out.read_text()) if out.is_file() else {}
    if header or not rec:
        rec.update(head)
    rec.setdefault("parity", {}).update(rows)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rec, indent=1) + "\n")


def policy_main(args, names, record) -> int:
    """``--policy``: every saved seed's deterministic policy in both engines, pooled per setting."""
    from shed_jax.training import load_policy, policy_student

    # only the networks and observation statistics are read: one env slot keeps the start-up cheap
    student = policy_student(BipedalWalker(), "bipedal", args.policy)
    states = load_policy(student, args.policy)
    seeds = int(states.obs_norm.count.shape[0])
    thetas = [jax.tree_util.tree_map(lambda x: x[i], states) for i in range(seeds)]
    controller = policy_controller(student)
    act = jax.jit(controller[0])  # (theta, obs) -> (action, carry): one compile for every seed
    rows = {}
    for name in names:
        level, gym_id = SETTINGS[name]
        limit = int(LEVELS[level]().max_steps)
        per_side = {"gym": [], "ours": []}  # each seed's episodes
        per_seed = []
        ours = ([None] * seeds if args.gym_only else
                jax_episodes(level, args.episodes, args.seed, min(args.chunk, args.episodes), controller, thetas))
        for i, theta in enumerate(thetas):
            sides = {}
            if not args.jax_only:
                sides["gym"] = gym_episodes(gym_id, args.episodes, args.seed + 1000 * i,
                                            policy=lambda s: np.asarray(act(theta, jnp.asarray(s, jnp.float32))[0], np.float64))
            if not args.gym_only:
                sides["ours"] = ours[i]
            for side, d in sides.items():
                per_side[side].append(d)
            per_seed.append({f"{side}_mean": float(np.mean(d["ret"])) for side, d in sides.items()})
            print(f"{name} seed {i}: " + "  ".join(f"{k} {v:.1f}" for k, v in per_seed[-1].items()), flush=True)
        row = {"episodes_per_seed": args.episodes, "seeds": seeds, "policy": args.policy, "deterministic": True,
               "per_seed": per_seed, **{k: record[k] for k in PROVENANCE}}
        for side, ds in per_side.items():
            if ds:
                d = {k: np.concatenate([e[k] for e in ds]) for k in ("ret", "length", "fall", "x")}
                d["obstacles"] = [ob for e in ds for ob in e["obstacles"]]
                o = summarize(d["ret"], d["length"], d["fall"])
                row.update({f"{side}_{k}": o[k] for k in ("mean", "se", "std", "fall", "length", "quartiles")})
                row.update(site_fields(side, d, limit))
        if "gym_mean" in row and "ours_mean" in row:
            row["pass"] = passes(dict(mean=row["gym_mean"], se=row["gym_se"], fall=row["gym_fall"]),
                                 dict(mean=row["ours_mean"], se=row["ours_se"], fall=row["ours_fall"]))
            print(f"policy {name}: gym {row['gym_mean']:.1f} ours {row['ours_mean']:.1f} "
                  f"parity {'PASS' if row['pass'] else 'FAIL'}", flush=True)
        rows[f"{args.tag}_{name}"] = row
    if args.out:  # add the policy rows to an existing record, keeping its other rows and header
        write_record(args.out, {k: record[k] for k in PROVENANCE}, rows, header=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
