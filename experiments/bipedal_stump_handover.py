"""Stump hand-over: the same walker state in front of a stump, in Box2D and in ours, and where each goes.

The PPO policy trained in our walker gets over stumps in our engine that stop or throw it in
Gymnasium's Box2D (docs/bipedal.md, "Where the policy's Hardcore episodes end"). This experiment
separates the physics from the observations. It plays the policy (deterministic, every saved seed) in
Gymnasium's ``BipedalWalkerHardcore-v3`` on the parity harness's seeds; the first time the hull comes
within ``--before`` metres of a stump, it snapshots Box2D's state (``envs.bipedal.parity.gym_state``:
bodies, joint and contact impulses, contact flags) and goes on from there, for ``--horizon`` steps, in:

* ``box2d``: Gymnasium's own episode (the reference);
* ``box2d_perturbed``: the same, with the hull's velocity changed by ``--perturb`` m/s at the
  snapshot (how often a stump's outcome flips by chance: the noise floor of any comparison);
* ``box2d_our_lidar``: Box2D's physics, the policy fed our lidar (``envs.walker.lidar``, the
  rasterised profile) at Box2D's hull instead of Box2D's ray casts;
* ``ours``: our engine from the handed-over state, closed loop on its own observations;
* ``ours_exact_lidar``: ours, the policy fed an exact ray cast against Gymnasium's fixtures (the
  polyline's edges and the obstacle boxes) instead of our lidar;
* ``ours_open_loop``: ours replaying Box2D's actions (physics alone, no feedback).

Each run is classified at the stump: ``passed`` (the hull beyond the stump's far side plus
``--pass-margin`` before any fall), ``fell`` (reward -100 first) or ``stopped`` (neither within the
horizon). The record holds the outcome counts per run, the confusion of each run against ``box2d``,
and how far our lidar is from Box2D's along Box2D's trajectories::

    python -m experiments.bipedal_stump_handover \\
        --policy docs/results/bipedal_ppo_flat_h200_2026-12-02/policy.msgpack --episodes 40 \\
        --out docs/results/bipedal_stump_handover.json

``--options`` adds runs of ours with other ``BipedalOptions`` (e.g. ``toi_velocity_iterations=None``),
one compile each.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

OUTCOMES = ("passed", "stopped", "fell")


def classify(xs, fell_at, x_pass) -> str:
    """``xs`` (n,) hull x after each step, ``fell_at`` the step index of a fall (or None), the x to pass."""
    xs = np.asarray(xs)
    beyond = np.nonzero(xs > x_pass)[0]
    first_pass = int(beyond[0]) if beyond.size else None
    if fell_at is not None and (first_pass is None or fell_at <= first_pass):
        return "fell"
    return "passed" if first_pass is not None else "stopped"


def episode_encounters(xs, fell_at, stumps, before, horizon, pass_margin) -> list[str]:
    """A whole episode's stump encounters, classified as the hand-over's: for each stump whose
    ``x0 - before`` the hull reaches before it is past ``x0`` (``xs`` (n,) hull x after each step, the
    start at the created x), the outcome over the next ``horizon`` steps."""
    xs = np.asarray(xs)
    out = []
    for x0, x1, _ in stumps:
        reach = np.nonzero(xs >= x0 - before)[0]
        if not reach.size or xs[reach[0]] > x0:
            continue
        t0 = int(reach[0]) + 1  # the step after the one that reached it, as the hand-over's snapshot
        seg = xs[t0:t0 + horizon]
        f = fell_at - t0 if fell_at is not None and 0 <= fell_at - t0 < horizon else None
        out.append(classify(seg, f, x1 + pass_margin))
    return out


def exact_lidar(terrain, origin):
    """Gymnasium's lidar (10 rays, ``b2World.RayCast`` keeping the closest terrain fixture) against our
    ``Terrain`` as Box2D's fixtures: the polyline's 199 edges and the valid boxes' four sides."""
    from envs.walker import constants as C
    from envs.walker import lidar as L

    p0 = jnp.stack([terrain.x[:-1], terrain.y[:-1]], -1)
    p1 = jnp.stack([terrain.x[1:], terrain.y[1:]], -1)
    b = terrain.boxes
    corners = jnp.stack([jnp.stack([b[:, 0], b[:, 2]], -1), jnp.stack([b[:, 1], b[:, 2]], -1),
                         jnp.stack([b[:, 1], b[:, 3]], -1), jnp.stack([b[:, 0], b[:, 3]], -1)], 1)  # (K, 4, 2)
    q0 = corners.reshape(-1, 2)
    q1 = jnp.roll(corners, -1, axis=1).reshape(-1, 2)
    a = jnp.concatenate([p0, q0])
    e = jnp.concatenate([p1, q1]) - a
    ok = jnp.concatenate([jnp.ones((p0.shape[0],), bool), jnp.repeat(terrain.box_valid, 4)])
    d = jnp.asarray(L.RAY_DIRS) * C.LIDAR_RANGE
    cross = lambda u, v: u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]  # noqa: E731
    ap = a[None] - origin[None, None]
    denom = cross(d[:, None], e[None])
    safe = jnp.where(jnp.abs(denom) > 1e-9, denom, 1.0)
    t = cross(ap, e[None]) / safe
    s = cross(ap, d[:, None]) / safe
    hit = ok[None] & (jnp.abs(denom) > 1e-9) & (t >= 0.0) & (t <= 1.0) & (s >= 0.0) & (s <= 1.0)
    return jnp.min(jnp.where(hit, t, 1.0), axis=1)


# ------------------------------------------------------------------ Box2D side
def gym_runs(act, thetas, episodes, seed, before, horizon, perturb, pass_margin, walker):
    """Every stump encounter of the policy in Gymnasium Hardcore: its snapshot (our state), Box2D's
    actions from there, and the three Box2D runs' outcomes; plus our lidar against Box2D's there."""
    import gymnasium as gym

    from envs.bipedal import parity
    from envs.walker import lidar as L

    lidar = jax.jit(lambda profile, pos: L.lidar(profile, walker.grid, pos))
    # One fresh env (a new b2World) per episode and per replay: Gymnasium's reset reuses its world, and
    # the broad-phase proxies left by earlier episodes change the order of Box2D's contacts, so the same
    # seed and actions give another trajectory in a world with another history (seed 3000: hull at x 22.0
    # or 25.1 after 400 steps). In fresh worlds a replay reaches the snapshot's state exactly.
    env = u = None

    def fresh():
        nonlocal env, u
        if env is not None:
            env.close()
        env = gym.make("BipedalWalkerHardcore-v3")
        u = env.unwrapped

    encounters, episodes_out = [], []

    def policy(theta, s):
        return np.asarray(act(theta, jnp.asarray(s, jnp.float32)), np.float64)

    def play(ep_seed, theta, actions_to, start, mode, limit, profile, snapshot_com):
        """Replay ``actions_to`` (the episode's first ``start`` actions), then from there the policy for
        ``limit`` steps with ``mode``: None, "perturb" or "our_lidar". Returns (xs, fell_at)."""
        fresh()
        s, _ = env.reset(seed=ep_seed)
        for a in actions_to[:start]:
            s, *_ = env.step(a)
        offset = float(np.max(np.abs(parity.gym_bodies(u)["com"] - snapshot_com)))  # 0 when the replay is exact
        if mode == "perturb":
            v = u.hull.linearVelocity
            u.hull.linearVelocity = (v[0] + perturb, v[1])
        xs, fell_at = [], None
        for k in range(limit):
            obs = np.array(s)
            if mode == "our_lidar":
                obs[14:] = np.asarray(lidar(profile, jnp.asarray(tuple(u.hull.position), jnp.float32)))
            s, r, term, trunc, _ = env.step(policy(theta, obs))
            xs.append(float(u.hull.position.x))
            if term or trunc:
                fell_at = k if (term and r == -100) else None
                break
        return xs, fell_at, offset

    from envs.walker import terrain as T

    for i, theta in enumerate(thetas):
        for ep in range(episodes):
            ep_seed = seed + 1000 * i + ep
            fresh()
            s, _ = env.reset(seed=ep_seed)
            terrain = parity.gym_terrain(u, walker.options.max_boxes)
            terrain_profile = [T.rasterise(terrain, walker.grid)]
            obstacles = parity.gym_obstacles(u)
            stumps = [ob for ob in obstacles if ob[2] == "stump"]
            pending = list(stumps)
            actions, xs, obs_log, pos_log, fell_at, snaps = [], [], [s], [tuple(u.hull.position)], None, []
            prev_angle = parity.gym_bodies(u)["angle"]
            start = parity.gym_state(u, walker, terrain, None, time=0, episode_return=0.0)
            ret, t = 0.0, 0
            while True:
                x = float(u.hull.position.x)
                while pending and x > pending[0][0]:  # passed the start of a stump without a snapshot
                    pending.pop(0)
                if pending and x >= pending[0][0] - before:
                    snaps.append(dict(step=t, stump=pending.pop(0), state=parity.gym_state(
                        u, walker, terrain, prev_angle, time=t, episode_return=ret), obs=np.array(s),
                                      com=parity.gym_bodies(u)["com"]))
                a = policy(theta, s)
                prev_angle = parity.gym_bodies(u)["angle"]
                s, r, term, trunc, _ = env.step(a)
                ret += r
                t += 1
                actions.append(a)
                xs.append(float(u.hull.position.x))
                obs_log.append(s)
                pos_log.append(tuple(u.hull.position))
                if term or trunc:
                    fell_at = t - 1 if (term and r == -100) else None
                    break
            episodes_out.append(dict(seed=i, episode=ep_seed, state=start, xs=np.asarray(xs, np.float32),
                                     fell_at=fell_at, stumps=stumps, obstacles=obstacles))
            for sn in snaps:
                t0, (x0, x1, _) = sn["step"], sn["stump"]
                x_pass = x1 + pass_margin
                n = min(horizon, len(xs) - t0)
                f = fell_at - t0 if fell_at is not None and fell_at - t0 < horizon else None
                row = dict(seed=i, episode=ep_seed, step=t0, stump=[x0, x1], x_pass=x_pass, state=sn["state"],
                           obs_gym=sn["obs"], box2d=classify(xs[t0:t0 + n], f, x_pass), box2d_steps=n)
                acts = np.zeros((horizon, 4), np.float32)
                acts[:n] = np.asarray(actions[t0:t0 + n])
                row["actions"] = acts
                # our lidar at Box2D's hull along Box2D's run from the snapshot, against Box2D's own
                d = np.stack([np.abs(np.asarray(lidar(terrain_profile[0], jnp.asarray(pos_log[t0 + k], jnp.float32)))
                                     - np.asarray(obs_log[t0 + k][14:])) for k in range(n + 1)])
                row["lidar_diff"] = d  # (n + 1, 10)
                for mode, name in (("perturb", "box2d_perturbed"), ("our_lidar", "box2d_our_lidar")):
                    pxs, pf, off = play(ep_seed, theta, actions, t0, mode, horizon, terrain_profile[0], sn["com"])
                    row[name] = classify(pxs, pf, x_pass)
                    row["replay_offset"] = max(row.get("replay_offset", 0.0), off)
                encounters.append(row)
            print(f"[handover] seed {i} episode {ep_seed}: {len(xs)} steps, end x {xs[-1]:.1f}, {len(stumps)} stumps at {[round(o[0], 1) for o in stumps]}, "
                  f"encounters {[e['box2d'] + '/' + e['box2d_perturbed'] + '/' + e['box2d_our_lidar'] for e in encounters[len(encounters) - len(snaps):]]}",
                  flush=True)
    if env is not None:
        env.close()
    return encounters, episodes_out


# ------------------------------------------------------------------ our side
def ours_runs(walker, student, thetas, encounters, horizon, variants, chunk):
    """Our engine from each encounter's handed-over state, for each ``variants`` entry (name, exact
    lidar, open loop): hull x and fall flag after each step, (rows, horizon) per variant."""
    from envs.walker.levels import LEVELS

    params = LEVELS["Hardcore"]()

    def observe(state, exact):
        obs = walker.observation(state.world, state.leg_contact, state.profile)
        lid = exact_lidar(state.terrain, walker.hull_origin(state.world))
        return jnp.where(exact, obs.at[14:].set(lid), obs)

    def one(state, theta, actions, exact, open_loop):
        def body(carry, inp):
            obs, st, done_before = carry
            k, a_rec = inp
            a = jnp.where(open_loop, a_rec, student.act(theta, jax.random.PRNGKey(0), obs, deterministic=True))
            _, st, reward, done, info = walker.step_without_reset(k, st, a, params)
            obs = observe(st, exact)
            fell = info["terminated"] & (reward == -100.0)
            return (obs, st, done_before | done), (info["x"], fell & ~done_before, done_before,
                                                    walker.hull_origin(st.world))

        carry = (observe(state, exact), state, jnp.bool_(False))
        keys = jax.random.split(jax.random.PRNGKey(1), horizon)
        _, (x, fell, dead, hull) = jax.lax.scan(body, carry, (keys, actions))
        return x, fell, dead, hull

    run = jax.jit(jax.vmap(one))
    n = len(encounters)
    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    states = [e["state"] for e in encounters]
    th = [thetas[e["seed"]] for e in encounters]
    acts = [jnp.asarray(e["actions"]) for e in encounters]
    rows = [(s, t, a, ex, ol) for ex, ol in [(v[1], v[2]) for v in variants] for s, t, a in zip(states, th, acts)]
    out = []
    for i in range(0, len(rows), chunk):
        part = rows[i:i + chunk]
        pad = chunk - len(part)
        part = part + part[:1] * pad  # one compiled shape
        res = run(stack([r[0] for r in part]), stack([r[1] for r in part]), jnp.stack([r[2] for r in part]),
                  jnp.asarray([r[3] for r in part]), jnp.asarray([r[4] for r in part]))
        res = [np.asarray(r)[: len(part) - pad] for r in res]
        out.append(res)
        print(f"[handover] ours: rows {i + len(part) - pad} of {len(rows)}", flush=True)
    x, fell, dead, hull = (np.concatenate([o[j] for o in out]) for j in range(4))
    results = {}
    for v, (name, _, _) in enumerate(variants):
        sl = slice(v * n, (v + 1) * n)
        results[name] = dict(x=x[sl], fell=fell[sl], dead=dead[sl], hull=hull[sl])
    return results


def ours_outcomes(res, encounters, horizon) -> list[str]:
    out = []
    for j, e in enumerate(encounters):
        alive = ~res["dead"][j]
        xs = res["x"][j][alive]
        f = np.nonzero(res["fell"][j])[0]
        out.append(classify(xs, int(f[0]) if f.size else None, e["x_pass"]))
    return out


def confusion(ref, other) -> dict:
    """{ref outcome: {other outcome: count}}."""
    return {a: {b: int(sum(1 for r, o in zip(ref, other) if r == a and o == b)) for b in OUTCOMES} for a in OUTCOMES}


def counts(outcomes) -> dict:
    return {k: int(sum(1 for o in outcomes if o == k)) for k in OUTCOMES}


def parse_options(text: str) -> dict:
    """``k=v,k=v`` -> BipedalOptions keyword arguments (ints, None, true/false)."""
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        k, eq, v = item.partition("=")
        v = v.strip()
        if not eq or not k.strip():
            raise ValueError(f"expected K=V items separated by commas, got {item!r}")
        try:
            out[k.strip()] = None if v == "None" else (v.lower() == "true" if v.lower() in ("true", "false") else int(v))
        except ValueError:
            raise ValueError(f"{k.strip()}: expected an integer, None, true or false, got {v!r}") from None
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", required=True, help="policy.msgpack of 'python -m shed_jax ppo --env bipedal'")
    p.add_argument("--episodes", type=int, default=40, help="Gymnasium episodes per saved seed")
    p.add_argument("--seed", type=int, default=0, help="episode seeds seed + 1000 i + e, as the parity harness")
    p.add_argument("--before", type=float, default=1.5, help="snapshot when the hull is this far before a stump (m)")
    p.add_argument("--horizon", type=int, default=200, help="steps from the snapshot")
    p.add_argument("--pass-margin", type=float, default=1.0, help="passed: hull x beyond the stump's far side + this")
    p.add_argument("--perturb", type=float, default=1e-3, help="box2d_perturbed: hull velocity change (m/s)")
    p.add_argument("--chunk", type=int, default=128, help="our rows per compiled batch")
    p.add_argument("--options", action="append", default=[], metavar="K=V,...",
                   help="an extra run of ours (closed loop and open loop) with these BipedalOptions")
    p.add_argument("--whole-episodes", type=int, default=0, metavar="N",
                   help="also play the first N Gymnasium episodes whole in ours, from Box2D's state after its reset "
                        "on the same terrain, and count each engine's stump encounters (2,000 steps each: slow on a CPU)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    t_start = time.time()
    from envs.bipedal import BipedalWalker
    from experiments.checkpoint_size import device_line
    from shed_jax.runtime import provenance
    from shed_jax.training import load_policy, policy_student

    if args.episodes < 1 or args.horizon < 1 or args.chunk < 1:
        p.error("--episodes, --horizon and --chunk must be integers >= 1")
    try:  # every walker is built before the long Box2D phase: a bad --options fails here, in one line
        extra = [(opts, BipedalWalker(**opts)) for opts in map(parse_options, args.options)]
    except (TypeError, ValueError) as err:
        p.error(f"--options: {err}")
    walker = BipedalWalker()
    student = policy_student(walker, "bipedal", args.policy)
    states = load_policy(student, args.policy)
    thetas = [jax.tree_util.tree_map(lambda x: x[i], states) for i in range(int(states.obs_norm.count.shape[0]))]
    act = jax.jit(lambda theta, obs: student.act(theta, jax.random.PRNGKey(0), obs, deterministic=True))
    t = time.time()
    enc, eps = gym_runs(act, thetas, args.episodes, args.seed, args.before, args.horizon, args.perturb,
                        args.pass_margin, walker)
    t_gym = time.time() - t
    print(f"[handover] {len(enc)} stump encounters, Box2D side {t_gym:.0f} s", flush=True)
    if not enc:
        print(f"[handover] no episode came within {args.before:g} m of a stump: nothing to compare (more --episodes?)",
              file=sys.stderr)
        return 1
    outcomes = {name: [e[name] for e in enc] for name in ("box2d", "box2d_perturbed", "box2d_our_lidar")}
    t = time.time()
    res = ours_runs(walker, student, thetas, enc, args.horizon,
                    [("ours", False, False), ("ours_exact_lidar", True, False), ("ours_open_loop", False, True)],
                    args.chunk)
    t_ours = time.time() - t
    for name, r in res.items():
        outcomes[name] = ours_outcomes(r, enc, args.horizon)
    for opts, w in extra:
        tag = "ours_" + "_".join(f"{k}={v}" for k, v in opts.items())
        r2 = ours_runs(w, student, thetas, enc, args.horizon, [(tag, False, False), (tag + "_open_loop", False, True)],
                       args.chunk)
        for name, r in r2.items():
            outcomes[name] = ours_outcomes(r, enc, args.horizon)
    # whole episodes on the same terrains from the same start (Box2D's state after its reset handed over)
    t = time.time()
    limit = 2000
    eps = eps[: args.whole_episodes]
    for e in eps:
        e["actions"] = np.zeros((limit, 4), np.float32)
    whole = ours_runs(walker, student, thetas, eps, limit, [("ours", False, False)], args.chunk)["ours"] if eps else None
    t_whole = time.time() - t
    from envs.bipedal import parity

    episodes = {}
    for side in ("box2d", "ours") if eps else ():
        ends, falls, xs_end, lens, enc_out = [], [], [], [], []
        for j, e in enumerate(eps):
            if side == "box2d":
                xs, fell_at = e["xs"], e["fell_at"]
            else:
                alive = ~whole["dead"][j]
                xs = whole["x"][j][alive]
                f = np.nonzero(whole["fell"][j])[0]
                fell_at = int(f[0]) if f.size else None
            falls.append(fell_at is not None)
            lens.append(len(xs))
            xs_end.append(float(xs[-1]))
            enc_out += episode_encounters(xs, fell_at, e["stumps"], args.before, args.horizon, args.pass_margin)
        falls, lens = np.asarray(falls), np.asarray(lens)
        obstacles = [e["obstacles"] for e in eps]
        episodes[side] = dict(
            fall=float(falls.mean()), length=float(lens.mean()),
            fall_sites=parity.end_sites(xs_end, falls, obstacles),
            limit_sites=parity.end_sites(xs_end, ~falls & (lens >= limit), obstacles),
            stump_encounters=len(enc_out), stump_encounters_per_episode=len(enc_out) / len(eps),
            stump_outcomes=counts(enc_out))
    print(f"[handover] whole episodes in ours: {t_whole:.0f} s; " + json.dumps(episodes), flush=True)
    lid = np.concatenate([e["lidar_diff"] for e in enc])
    lid_snap = np.stack([e["lidar_diff"][0] for e in enc])
    summary = {name: counts(o) for name, o in outcomes.items()}
    record = {**provenance("experiments.bipedal_stump_handover", argv), "device": device_line(),
              "versions": versions(), "policy": args.policy, "episodes_per_seed": args.episodes,
              "seeds": len(thetas), "before_m": args.before, "horizon": args.horizon, "pass_margin_m": args.pass_margin,
              "perturb_m_s": args.perturb, "encounters": len(enc), "wall_s": {"box2d": round(t_gym), "ours": round(t_ours), "ours_whole_episodes": round(t_whole),
                                                                              "total": round(time.time() - t_start)},
              "box2d_replay_max_offset_m": float(max(e["replay_offset"] for e in enc)),
              "outcomes": summary, **({"whole_episodes": dict(episodes=len(eps), **episodes)} if eps else {}),
              "confusion_vs_box2d": {name: confusion(outcomes["box2d"], o) for name, o in outcomes.items() if name != "box2d"},
              "agreement_vs_box2d": {name: float(np.mean([a == b for a, b in zip(outcomes["box2d"], o)]))
                                     for name, o in outcomes.items() if name != "box2d"},
              "lidar_abs_diff": {"along_box2d_runs": {"mean": float(lid.mean()), "p99": float(np.percentile(lid, 99)),
                                                      "max": float(lid.max()),
                                                      "steps_with_any_ray_over_0.01": float(np.mean(lid.max(1) > 0.01))},
                                 "at_snapshots": {"mean": float(lid_snap.mean()), "max": float(lid_snap.max())},
                                 "per_ray_mean_along_runs": [float(v) for v in lid.mean(0)]},
              "rows": [dict(seed=e["seed"], episode=e["episode"], step=e["step"], stump=[round(e["stump"][0], 4),
                                                                                        round(e["stump"][1], 4)],
                            **{name: outcomes[name][j] for name in outcomes}) for j, e in enumerate(enc)]}
    print(json.dumps({k: record[k] for k in ("encounters", "outcomes", "agreement_vs_box2d", "whole_episodes",
                                             "lidar_abs_diff") if k in record}, indent=1))
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(record, indent=1) + "\n")
    return 0


def versions() -> dict:
    import importlib.metadata as md

    out = {"python": platform.python_version(), "jax": jax.__version__}
    for name in ("gymnasium", "box2d", "box2d-py"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


if __name__ == "__main__":
    raise SystemExit(main())
