"""Why episodes end, ours against Gymnasium, for one gravity: the g -1 parity gap (docs/lander.md).

For N episodes of Gymnasium's heuristic on each side: the mean return, how episodes end (landed,
out of bounds |x| >= 1, hull contact, truncated), the first step with a leg on the ground, and the
vertical speed and angle (observation units) at that step.

    python experiments/lander_crash_causes.py N GRAVITY SEED     # e.g. 1000 -1.0 1

Ours runs as one vmapped scan on the CPU here; Gymnasium uses seeds 0..N-1.
"""
import sys, numpy as np, jax, jax.numpy as jnp, time
from envs.lander.env import LunarLander, make_params
from envs.lander.heuristic import heuristic
from envs.lander.parity import _np_heuristic
N = int(sys.argv[1]) if len(sys.argv) > 1 else 300
G = float(sys.argv[2]) if len(sys.argv) > 2 else -1.0
T = 1000

def summarize(name, obs_t, rew_t, done_t):
    # obs_t [N, T, 8] obs after each step; rew_t [N, T]; done_t [N, T]
    res = dict(oob=0, hull=0, landed=0, trunc=0)
    first_contact, t_end, x_end, vy_contact, ang_contact = [], [], [], [], []
    for i in range(obs_t.shape[0]):
        d = np.flatnonzero(done_t[i]); e = d[0] if len(d) else T - 1
        r = rew_t[i, e]
        o = obs_t[i, :e + 1]
        c = np.flatnonzero((o[:, 6] > 0) | (o[:, 7] > 0))
        fc = c[0] if len(c) else -1
        first_contact.append(fc); t_end.append(e + 1)
        if fc >= 0:
            vy_contact.append(o[fc, 3]); ang_contact.append(o[fc, 4])
        if r == 100: res["landed"] += 1
        elif r == -100:
            if abs(obs_t[i, e, 0]) >= 1 or (e > 0 and abs(obs_t[i, e - 1, 0]) > 0.95): res["oob"] += 1
            else: res["hull"] += 1
        else: res["trunc"] += 1
    fc = np.array(first_contact)
    rets = np.array([rew_t[i, :(np.flatnonzero(done_t[i])[0] + 1) if done_t[i].any() else T].sum() for i in range(obs_t.shape[0])])
    print(f"{name}: mean return {rets.mean():.1f} ± {rets.std()/np.sqrt(len(rets)):.1f} {res} | first leg contact step median {np.median(fc[fc>=0]):.0f} (none {np.mean(fc<0):.2f}) | "
          f"vy_obs at contact mean {np.mean(vy_contact):.3f} | angle at contact mean|.| {np.mean(np.abs(ang_contact)):.3f} | len {np.mean(t_end):.0f}")

# gym side
import gymnasium as gym
t = time.time()
env = gym.make("LunarLander-v3", gravity=G, max_episode_steps=T)
O = np.zeros((N, T, 8), np.float32); R = np.zeros((N, T), np.float32); D = np.zeros((N, T), bool)
for ep in range(N):
    obs, _ = env.reset(seed=ep)
    for k in range(T):
        obs, r, term, tr, _ = env.step(_np_heuristic(obs, False))
        O[ep, k], R[ep, k], D[ep, k] = obs, r, term or tr
        if term or tr: break
summarize("gym", O, R, D); print(f"gym {time.time()-t:.0f}s", flush=True)

# ours
t = time.time()
lander = LunarLander(continuous=False)
levels = make_params(max_steps=np.full(N, T), gravity=np.full(N, G, np.float32), enable_wind=np.zeros(N, bool),
                     wind_power=np.full(N, 15.0, np.float32), turbulence_power=np.full(N, 1.5, np.float32))
def one(key, p):
    k0, k1 = jax.random.split(key)
    obs, s = lander.reset(k0, p)
    def body(c, k):
        obs, s, done_before = c
        obs2, s, r, d, info = lander.step(k, s, heuristic(obs, False), p)
        o = jnp.where(d, info["final_obs"], obs2)
        return (obs2, s, done_before | d), (o, r, d & ~done_before, done_before)
    _, (o, r, d, before) = jax.lax.scan(body, (obs, s, jnp.bool_(False)), jax.random.split(k1, T))
    return o, r, d
o, r, d = jax.jit(jax.vmap(one))(jax.random.split(jax.random.PRNGKey(int(sys.argv[3]) if len(sys.argv) > 3 else 0), N), levels)
summarize("ours", np.asarray(o), np.asarray(r), np.asarray(d)); print(f"ours {time.time()-t:.0f}s")
