"""A lone shin thrown at a stump's top-left corner, in pybox2d 2.3.10 and in envs.physics2d (docs/bipedal.md,
"A lone shin thrown at a stump").

    python -m experiments.bipedal_shin_stump [--grids base,wide] [--sides 1,2]
        [--configs walker,toi_events3,toi_velocity180,no_toi] [--cases 384] [--seed 0]
        [--out docs/results/bipedal_shin_stump.json]

Gymnasium's BipedalWalker lower leg (the walker model's own polygon, 0.21 x 1.13 m, density 1,
friction 0.2), alone with no joints, on a ground of one Box2D edge per terrain column (friction 2.5)
with a stump: a square box of ``side`` terrain steps whose left face is 3 terrain steps from x = 0.
Each case starts the shin left of the face, its lowest point near the stump's top, thrown to the
right with a spin; 25 steps at 50 Hz with Box2D's 180 velocity / 60 position iterations. Per grid
(``GRIDS``: base, wide) and stump side (1, 2 terrain steps), ``--cases`` uniform random starts
(``--seed``) are rolled out in pybox2d with continuous physics on and off, and in physics2d (vmapped,
on the backend JAX runs on) under each configuration of ``CONFIGS``: ``BipedalOptions`` fields over
the walker's defaults, the solver settings taken from the walker's own model
(``BipedalWalker(**fields).model.config``); each is compared with pybox2d's roll-out with the same
continuous physics setting.

Per grid and configuration the record holds the outcome counts in both engines (by the final centre
x: stopped before the stump's face, on top of it, beyond it), their 3 x 3 confusion and its
off-diagonal count, the position difference (median / p90 / max) at steps 1, 5 and 25, the cases
more than 1 cm apart at step 25 and at any step, and each engine's deepest penetration into the stump
(``penetration``; negative: never overlapping). Per grid it also holds Box2D's time-of-impact events
per step (``box2d_toi_events``: a replay of every step, 5-7 s a grid). physics2d's events are not
counted: that needs a second, TOI-less physics step beside every step. Nothing per case is kept.
On a 2-core CPU the whole run takes about 5 minutes (300 s on 2026-12-03; 8 physics2d compiles).
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time

import numpy as np

STEPS = 25
OUTCOMES = ("stopped", "on_top", "beyond")
#: initial-condition ranges (uniform, drawn in this order): speed vx, vy (m/s), angle (rad), spin omega
#: (rad/s), d = the shin's lowest point minus the stump's top (m), gap = the stump's face minus the
#: shin's rightmost point (m); and the terrain columns [-2, last) that carry a ground edge
GRIDS = {
    "base": dict(ranges=dict(vx=(1.0, 6.0), vy=(-2.0, 1.0), angle=(-0.6, 0.6), omega=(-5.0, 5.0), d=(-0.15, 0.15),
                             gap=(0.01, 0.06)), last_column=16),
    "wide": dict(ranges=dict(vx=(1.0, 12.0), vy=(-4.0, 2.0), angle=(-1.0, 1.0), omega=(-15.0, 15.0), d=(-0.25, 0.25),
                             gap=(0.01, 0.3)), last_column=26),
}
SIDES = (1, 2)
#: name -> BipedalOptions fields over the walker's defaults (toi_events 1, 4 TOI velocity passes)
CONFIGS = {
    "walker": {},
    "toi_events3": {"toi_events": 3},
    "toi_velocity180": {"toi_velocity_iterations": None},  # None: Box2D's, the step's 180 (b2World::SolveTOI)
    "no_toi": {"continuous": False},
}
#: the walker's solver settings the record shows for each config
SOLVER_FIELDS = ("dt", "velocity_iterations", "position_iterations", "ground_friction", "edge_contacts", "continuous",
                 "toi_events", "toi_iterations", "toi_position_iterations", "toi_from_touching")
STUMP_COLUMN = 3  # the stump's left face, in terrain steps from x = 0


def terrain_step() -> float:
    from envs.walker import constants as C  # imported here: envs imports JAX, which the CLI's errors need not wait for

    return C.TERRAIN_STEP


def stump_box(side: int) -> tuple:
    """(x0, x1, y0, y1) of a stump of ``side`` terrain steps on the ground y = 0."""
    ts = terrain_step()
    return (STUMP_COLUMN * ts, (STUMP_COLUMN + side) * ts, 0.0, side * ts)


def ground_edges(grid: str) -> np.ndarray:
    """(S, 2, 2) float64: one edge per terrain column from column -2 to the grid's last."""
    ts = terrain_step()
    return np.asarray([((i * ts, 0.0), ((i + 1) * ts, 0.0)) for i in range(-2, GRIDS[grid]["last_column"])])


def shin_polygon():
    """The walker model's first lower leg as the only polygon of body 0."""
    from envs.bipedal import model as M

    walker = M.walker_model()
    return dataclasses.replace(walker.polygons[M.ISLAND_BODIES.index(M.LOWER[0])], body=0)


@functools.lru_cache(maxsize=None)
def shin_half() -> tuple:
    """The shin's half extents (hx, hy), from its polygon (a box centred on its origin)."""
    v = np.asarray(shin_polygon().vertices, np.float64)
    return tuple(float(h) for h in v.max(0))


def starts(grid: str, side: int, seed: int = 0, n: int = 384) -> dict:
    """``n`` random starts of ``GRIDS[grid]`` against a ``side``-step stump: the drawn arrays (vx, vy, angle,
    omega, d, gap; float64) and the shin's origin x, y that put its lowest point d above the stump's
    top and its rightmost point gap left of the face."""
    rng = np.random.default_rng(seed)
    out = {k: rng.uniform(lo, hi, n) for k, (lo, hi) in GRIDS[grid]["ranges"].items()}
    hx, hy = shin_half()
    a = np.abs(out["angle"])
    reach_y, reach_x = hy * np.cos(a) + hx * np.sin(a), hx * np.cos(a) + hy * np.sin(a)  # centre to lowest / rightmost
    x0, _, _, y1 = stump_box(side)
    out["y"] = y1 + out["d"] + reach_y
    out["x"] = x0 - out["gap"] - reach_x
    return out


def classify(traj: np.ndarray, stump: tuple) -> np.ndarray:
    """Outcome index into OUTCOMES of each trajectory (n, steps, >= 1) by its final centre x: 0 left of
    the stump's face, 1 from the face to the right side inclusive, 2 right of it."""
    x = np.asarray(traj)[:, -1, 0]
    return np.where(x < stump[0], 0, np.where(x <= stump[1], 1, 2))


def penetration(x, y, angle, half: tuple, stump: tuple) -> np.ndarray:
    """The shin's overlap depth with the stump, elementwise over x, y, angle (its centre and angle):
    the least overlap of their projections on the four face normals (separating-axis test, the shapes
    without Box2D's skin); > 0 overlapping by that depth, <= 0 apart (then minus the widest gap along
    those axes)."""
    x, y, angle = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (x, y, angle)))
    hx, hy = half
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    local = np.array([(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)])
    shin = np.stack([x[..., None] + c * local[:, 0] - s * local[:, 1],
                     y[..., None] + s * local[:, 0] + c * local[:, 1]], -1)  # (..., 4, 2)
    x0, x1, y0, y1 = stump
    box = np.array([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])
    axes = np.stack(np.broadcast_arrays(np.concatenate([c, s], -1), np.concatenate([-s, c], -1),
                                        np.array([1.0, 0.0]), np.array([0.0, 1.0])), -2)  # (..., 4 axes, 2)
    p = np.einsum("...kd,...ad->...ak", shin, axes)
    q = np.einsum("kd,...ad->...ak", box, axes)
    return (np.minimum(p.max(-1), q.max(-1)) - np.maximum(p.min(-1), q.min(-1))).min(-1)


def box2d_trajectories(b2, start: dict, edges: np.ndarray, stump: tuple, continuous: bool,
                       steps: int = STEPS) -> np.ndarray:
    """pybox2d's (n, steps, 3) x, y, angle of every start (envs.physics2d.box2d_reference)."""
    from envs.physics2d.box2d_reference import box_trajectory

    return np.stack([box_trajectory(b2, edges, (start["x"][i], start["y"][i]), float(start["angle"][i]), shin_half(),
                                    velocity=(start["vx"][i], start["vy"][i]), steps=steps, boxes=[stump],
                                    omega=start["omega"][i], continuous=continuous)
                     for i in range(len(start["x"]))])


def box2d_toi_events(b2, start: dict, edges: np.ndarray, stump: tuple, ref: np.ndarray) -> np.ndarray:
    """(n, steps) int: the time-of-impact events Box2D handled in each step of ``ref`` (pybox2d's
    trajectories with continuous physics on). 0 where the step, replayed with continuous physics off,
    ends where ``ref`` does; else the ``world.subStepping`` calls (one event each) that reach ``ref``'s
    end, followed by one that changes nothing; -1 where that does not happen within 8 calls."""
    from envs.physics2d import box2d_reference as R

    n, steps = ref.shape[:2]
    out = np.zeros((n, steps), np.int32)

    def world_before(i: int, k: int):
        world, body = R.box_world(b2, edges, (start["x"][i], start["y"][i]), float(start["angle"][i]), shin_half(),
                                  (start["vx"][i], start["vy"][i]), [stump], start["omega"][i])
        for _ in range(k):
            R.step(world)
        return world, body

    for i in range(n):
        for k in range(steps):
            world, body = world_before(i, k)
            world.continuousPhysics = False
            R.step(world)
            if R.box_pose(body) == list(ref[i, k]):
                continue
            world, body = world_before(i, k)
            world.subStepping = True
            out[i, k] = -1
            for calls in range(1, 9):
                R.step(world)
                pose = R.box_pose(body)
                if pose == list(ref[i, k]):
                    R.step(world)
                    out[i, k] = calls if R.box_pose(body) == pose else -1
                    break
    return out


def shin_model(fields: dict):
    """physics2d's model of the lone shin with the walker's solver config under BipedalOptions ``fields``."""
    from envs import physics2d
    from envs.bipedal import BipedalWalker

    return physics2d.make_model(1, (shin_polygon(),), (), BipedalWalker(**fields).model.config)


def physics2d_rollout(model, steps: int = STEPS):
    """A jitted ``(start arrays x, y, angle, vx, vy, omega (n,), ground (P, 2), edges (S, 2, 2), stump (1, 4))
    -> (n, steps, 3)`` x, y, angle of the shin's origin after each step, vmapped over the starts."""
    import jax
    import jax.numpy as jnp

    from envs import physics2d

    def one(x, y, angle, vx, vy, omega, ground, edges, stump):
        bodies = physics2d.bodies_from_origin(model, jnp.stack([x, y])[None], angle[None],
                                              vel=jnp.stack([vx, vy])[None], omega=omega[None])

        def body_fn(world, _):
            world, _ = physics2d.step(model, world, ground, -10.0, edges=edges, boxes=stump,
                                      edge_valid=jnp.ones(edges.shape[0], bool), box_valid=jnp.ones((1,), bool))
            return world, jnp.concatenate([physics2d.body_origin(model, world.bodies)[0], world.bodies.angle[:1]])

        return jax.lax.scan(body_fn, physics2d.init_world(model, bodies), None, length=steps)[1]

    return jax.jit(jax.vmap(one, in_axes=(0,) * 6 + (None,) * 3))


def physics2d_trajectories(rollout, start: dict, edges: np.ndarray, stump: tuple) -> np.ndarray:
    """``rollout`` (``physics2d_rollout``) of every start on ``edges`` and ``stump``, in float32."""
    import jax.numpy as jnp

    args = [jnp.asarray(start[k], jnp.float32) for k in ("x", "y", "angle", "vx", "vy", "omega")]
    ground = np.concatenate([edges[:1, 0], edges[:, 1]])
    return np.asarray(rollout(*args, jnp.asarray(ground, jnp.float32), jnp.asarray(edges, jnp.float32),
                              jnp.asarray([stump], jnp.float32)), np.float64)


def compare(ref: np.ndarray, ours: np.ndarray, stump: tuple) -> dict:
    """pybox2d's trajectories ``ref`` against physics2d's ``ours`` ((n, steps, 3) each): outcomes, their
    confusion (rows pybox2d, columns physics2d), position differences, deepest penetrations."""
    a, b = classify(ref, stump), classify(ours, stump)
    conf = np.zeros((3, 3), int)
    np.add.at(conf, (a, b), 1)
    dist = np.hypot(ref[..., 0] - ours[..., 0], ref[..., 1] - ours[..., 1])
    half = shin_half()
    deepest = lambda t: float(penetration(t[..., 0], t[..., 1], t[..., 2], half, stump).max())  # noqa: E731
    return {
        "outcomes": {"box2d": dict(zip(OUTCOMES, map(int, conf.sum(1)))),
                     "physics2d": dict(zip(OUTCOMES, map(int, conf.sum(0))))},
        "confusion": conf.tolist(), "off_diagonal": int(conf.sum() - np.trace(conf)),
        "position_difference_m": {f"step{s}": {"median": float(np.median(dist[:, s - 1])),
                                               "p90": float(np.percentile(dist[:, s - 1], 90)),
                                               "max": float(dist[:, s - 1].max())}
                                  for s in (1, 5, 25) if s <= dist.shape[1]},
        "over_1cm_last_step": int((dist[:, -1] > 0.01).sum()), "over_1cm_any_step": int((dist > 0.01).any(1).sum()),
        "max_penetration_m": {"box2d": deepest(ref), "physics2d": deepest(ours)},
    }


def toi_event_counts(events: np.ndarray) -> dict:
    """``box2d_toi_events``' counts: steps with one event, with two or more, cases with any, unresolved steps."""
    return {"steps_with_one": int((events == 1).sum()), "steps_with_two_or_more": int((events >= 2).sum()),
            "cases_with_any": int((events > 0).any(1).sum()), "unresolved": int((events < 0).sum())}


def run_grid(b2, grid: str, side: int, rollouts: dict, seed: int, cases: int) -> dict:
    """One grid and stump side: pybox2d's roll-outs (continuous physics as each config needs), Box2D's
    TOI events (with continuous physics on) and ``compare`` for each config of ``rollouts``
    (name -> ``physics2d_rollout``); prints one line per config."""
    start, edges, stump = starts(grid, side, seed, cases), ground_edges(grid), stump_box(side)
    continuous = {c: CONFIGS[c].get("continuous", True) for c in rollouts}
    t = time.perf_counter()
    ref = {on: box2d_trajectories(b2, start, edges, stump, on) for on in sorted(set(continuous.values()))}
    row = {"ranges": GRIDS[grid]["ranges"], "ground_edges": len(edges), "stump": list(stump),
           "box2d_seconds": round(time.perf_counter() - t, 1)}
    if True in ref:
        t = time.perf_counter()
        row["box2d_toi_events"] = {**toi_event_counts(box2d_toi_events(b2, start, edges, stump, ref[True])),
                                   "seconds": round(time.perf_counter() - t, 1)}
        print(f"{grid}_side{side} Box2D TOI events {row['box2d_toi_events']}", flush=True)
    row["configs"] = {}
    for c, rollout in rollouts.items():
        t = time.perf_counter()
        ours = physics2d_trajectories(rollout, start, edges, stump)
        row["configs"][c] = res = {**compare(ref[continuous[c]], ours, stump),
                                   "physics2d_seconds": round(time.perf_counter() - t, 1)}
        print(summary_line(f"{grid}_side{side}", c, res), flush=True)
    return row


def summary_line(name: str, config: str, res: dict) -> str:
    """``compare``'s result in one line: outcomes (stopped / on top / beyond), p90 position differences, etc."""
    counts = lambda engine: "/".join(map(str, res["outcomes"][engine].values()))  # noqa: E731
    p = res["position_difference_m"]
    pen = res["max_penetration_m"]
    return (f"{name:11s} {config:16s} box2d {counts('box2d')} physics2d {counts('physics2d')} off-diagonal "
            f"{res['off_diagonal']}  |dpos| p90 s1 {p['step1']['p90']:.1e} s5 {p['step5']['p90']:.1e} s25 "
            f"{p['step25']['p90']:.1e} max25 {p['step25']['max']:.2f}  >1cm s25 {res['over_1cm_last_step']} "
            f"any {res['over_1cm_any_step']}  max pen box2d {pen['box2d']:+.3f} physics2d {pen['physics2d']:+.3f}  "
            f"({res['physics2d_seconds']} s)")


def _names(text: str, valid, what: str) -> list:
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in names if t not in valid]
    if bad or not names:
        raise ValueError(f"unknown {what} {bad[0] if bad else text!r} (choose from {', '.join(map(str, valid))})")
    return names


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grids", default=",".join(GRIDS))
    ap.add_argument("--sides", default=",".join(map(str, SIDES)), help="stump sides in terrain steps")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--cases", type=int, default=384, help="random starts per grid and side")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="JSON record to write (docs/results/bipedal_shin_stump.json)")
    args = ap.parse_args(argv)
    try:
        grids = _names(args.grids, tuple(GRIDS), "grid")
        sides = [int(s) for s in _names(args.sides, tuple(map(str, SIDES)), "side")]
        configs = _names(args.configs, tuple(CONFIGS), "config")
        if args.cases < 1:
            raise ValueError(f"--cases must be >= 1, got {args.cases}")
        from envs.physics2d.box2d_reference import load_box2d

        b2 = load_box2d()
    except (ValueError, ImportError) as err:
        print(f"bipedal_shin_stump: {err}", file=sys.stderr)
        return 2

    from experiments import checkpoint_size as cs

    record = {**cs.record_header("experiments.bipedal_shin_stump", argv), "pybox2d": b2.__version__,
              "cases": args.cases, "seed": args.seed, "steps": STEPS, "outcomes": list(OUTCOMES),
              "configs": {}, "grids": {}}
    t = time.perf_counter()
    models = {c: shin_model(CONFIGS[c]) for c in configs}
    for c, m in models.items():  # the options and what the walker's model made of them
        record["configs"][c] = {"options": CONFIGS[c], "solver": {k: getattr(m.config, k) for k in SOLVER_FIELDS}}
    rollouts = {c: physics2d_rollout(m) for c, m in models.items()}  # each compiles once per edge count
    for grid in grids:
        for side in sides:
            record["grids"][f"{grid}_side{side}"] = run_grid(b2, grid, side, rollouts, args.seed, args.cases)
    record["seconds"] = round(time.perf_counter() - t, 1)
    print(f"total {record['seconds']} s")
    if args.out:
        import json
        import pathlib

        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(record, indent=1) + "\n")
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
