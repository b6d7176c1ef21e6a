"""The paper's diffusion check (section 4.1 and appendix; Figure 2).

A fixed random MLP f(s, a), s in R^5, a in R^3, plays the role of the student's capability dynamics:
real transitions are s' = f(s, a) + sigma * eps. The conditional DDPM (shed_jax.teacher.diffusion,
default configuration: K = 5, 3 x 256 Mish, buffer normaliser) is trained on (s, a, s') data from a
real buffer; then, at one fixed (s, a), 200 real and 200 synthetic s' are drawn and compared with
the per-dimension Wasserstein-1 distance and the energy distance, next to the noise floor (the same
distance between two independent sets of 200 real samples), per noise level sigma.

Run:  python experiments/diffusion_check.py [--out DIR] [--steps N] [--ema 0 0.995] [--quick]
Writes DIR/diffusion_check.json, DIR/diffusion_check.png (no EMA, the official setting) and
DIR/diffusion_check_ema0.995.png (sampling with an EMA of the weights); DIR defaults to $OUT or docs/.
CPU, a few minutes at the defaults.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import wasserstein_distance

from shed_jax.teacher.buffers import Transition, buffer_add_many, buffer_init, make_transition
from shed_jax.teacher.diffusion import DiffusionConfig, make_diffusion

STATE_DIM, ACTION_DIM = 5, 3
NOISE_LEVELS = (0.05, 1.0, 3.0, 10.0)


def random_mlp(key, in_dim=STATE_DIM + ACTION_DIM, hidden=32, out_dim=STATE_DIM, scale=3.0):
    """A fixed random tanh MLP f(x) = scale * tanh(x W1 + b1) W2 / sqrt(hidden): smooth, O(scale)."""
    k1, k2, k3 = jax.random.split(key, 3)
    w1 = jax.random.normal(k1, (in_dim, hidden)) / np.sqrt(in_dim)
    b1 = 0.5 * jax.random.normal(k2, (hidden,))
    w2 = jax.random.normal(k3, (hidden, out_dim)) / np.sqrt(hidden)
    return lambda s, a: scale * jnp.tanh(jnp.concatenate([s, a], -1) @ w1 + b1) @ w2


def make_dataset(key, f, n, sigma, noise="gaussian"):
    """n transitions with s ~ N(0, I_5), a ~ U[-1,1]^3, s' = f(s, a) + sigma * noise.

    noise 'gaussian': eps ~ N(0, I). noise 'bimodal': eps = +-2 (fair sign, shared by all dims) +
    0.25 N(0, I), a two-mode conditional distribution.
    """
    ks, ka, ke, kb = jax.random.split(key, 4)
    s = jax.random.normal(ks, (n, STATE_DIM))
    a = jax.random.uniform(ka, (n, ACTION_DIM), minval=-1.0, maxval=1.0)
    return s, a, f(s, a) + sigma * draw_noise(ke, kb, n, noise)


def draw_noise(ke, kb, n, noise):
    eps = jax.random.normal(ke, (n, STATE_DIM))
    if noise == "gaussian":
        return eps
    sign = jnp.where(jax.random.bernoulli(kb, 0.5, (n, 1)), 1.0, -1.0)
    return 2.0 * sign + 0.25 * eps


def fill_buffer(s, a, s_next):
    n = s.shape[0]
    buf = buffer_init(make_transition(STATE_DIM, ACTION_DIM), n)
    zeros = jnp.zeros((n,))
    return buffer_add_many(buf, Transition(s=s, u=a, r=zeros, s_next=s_next, done=zeros))


def train_model(key, buf, steps, config=None):
    model = make_diffusion(config or DiffusionConfig(STATE_DIM, ACTION_DIM))
    k_init, k_train = jax.random.split(key)
    state = jax.jit(model.init)(k_init)
    state, losses = jax.jit(model.train_steps, static_argnums=3)(state, k_train, buf, steps)
    return model, state, losses


def energy_distance(x, y) -> float:
    """V-statistic energy distance 2E|X-Y| - E|X-X'| - E|Y-Y'| (Euclidean), >= 0."""
    d = lambda p, q: np.mean(np.linalg.norm(p[:, None, :] - q[None, :, :], axis=-1))
    return float(2 * d(x, y) - d(x, x) - d(y, y))


def mean_w1(x, y) -> float:
    """Mean over dimensions of the 1-D Wasserstein-1 distance between the marginals."""
    return float(np.mean([wasserstein_distance(x[:, j], y[:, j]) for j in range(x.shape[1])]))


def compare_at_point(key, model, state, f, s0, a0, sigma, n=200, repeats=10, noise="gaussian"):
    """Distances real-vs-synthetic and real-vs-real (floor), each averaged over ``repeats`` draws."""
    sample = jax.jit(model.sample_next_state)
    s_rep = jnp.tile(s0[None], (n, 1))
    a_rep = jnp.tile(a0[None], (n, 1))
    out = {"w1": [], "w1_floor": [], "energy": [], "energy_floor": []}
    real_sets, syn_sets = [], []
    for r in range(repeats):
        k1, k2, k3, k4, k5, key = jax.random.split(key, 6)
        real1 = np.asarray(f(s_rep, a_rep) + sigma * draw_noise(k1, k4, n, noise))
        real2 = np.asarray(f(s_rep, a_rep) + sigma * draw_noise(k2, k5, n, noise))
        syn = np.asarray(sample(state, k3, s_rep, a_rep))
        out["w1"].append(mean_w1(real1, syn))
        out["w1_floor"].append(mean_w1(real1, real2))
        out["energy"].append(energy_distance(real1, syn))
        out["energy_floor"].append(energy_distance(real1, real2))
        real_sets.append(real1)
        syn_sets.append(syn)
    stats = {k: float(np.mean(v)) for k, v in out.items()}
    return stats, real_sets[0], syn_sets[0]


def run(steps=3000, num_data=4096, seed=0, out_dir="docs", ema_decays=(0.0, 0.995), batch_size=64):
    key = jax.random.PRNGKey(seed)
    k_f, k_pt, key = jax.random.split(key, 3)
    f = random_mlp(k_f)
    ks0, ka0 = jax.random.split(k_pt)
    s0 = jax.random.normal(ks0, (STATE_DIM,))
    a0 = jax.random.uniform(ka0, (ACTION_DIM,), minval=-1.0, maxval=1.0)
    os.makedirs(out_dir, exist_ok=True)
    results = []
    for ema in ema_decays:  # same data, training keys and evaluation keys for every setting
        samples = []
        k_run = key
        for sigma in NOISE_LEVELS:
            k_data, k_train, k_cmp, k_run = jax.random.split(k_run, 4)
            t0 = time.time()
            buf = fill_buffer(*make_dataset(k_data, f, num_data, sigma))
            cfg = DiffusionConfig(STATE_DIM, ACTION_DIM, batch_size=batch_size, ema_decay=ema)
            model, state, losses = train_model(k_train, buf, steps, cfg)
            stats, real, syn = compare_at_point(k_cmp, model, state, f, s0, a0, sigma)
            stats.update(sigma=sigma, ema_decay=ema, final_loss=float(np.mean(np.asarray(losses)[-100:])), seconds=time.time() - t0)
            results.append(stats)
            samples.append((real, syn))
            print(
                f"ema={ema:5.3f} sigma={sigma:5.2f}  W1 {stats['w1']:.4f} (floor {stats['w1_floor']:.4f})  "
                f"energy {stats['energy']:.4f} (floor {stats['energy_floor']:.4f})  loss {stats['final_loss']:.3f}  "
                f"{stats['seconds']:.0f}s",
                flush=True,
            )
        name = "diffusion_check.png" if ema == 0 else f"diffusion_check_ema{ema:g}.png"
        plot(samples, out_dir, name, f"ema_decay={ema:g}")
    meta = {
        "steps": steps, "batch_size": batch_size, "num_data": num_data, "seed": seed, "samples": 200, "repeats": 10,
        "device": jax.devices()[0].platform,
    }
    with open(os.path.join(out_dir, "diffusion_check.json"), "w") as fh:
        json.dump({"meta": meta, "results": results}, fh, indent=1)
    return results


def plot(samples, out_dir, name, title):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(samples), 3, figsize=(10, 2.4 * len(samples)))
    for row, ((real, syn), sigma) in enumerate(zip(samples, NOISE_LEVELS)):
        for j in range(3):
            ax = axes[row, j]
            bins = np.histogram_bin_edges(np.concatenate([real[:, j], syn[:, j]]), 30)
            ax.hist(real[:, j], bins, color="tab:red", alpha=0.55, label="real")
            ax.hist(syn[:, j], bins, color="tab:blue", alpha=0.55, label="synthetic")
            ax.set_title(f"noise {sigma:g}: s'_{j + 1}", fontsize=9)
            if row == 0 and j == 0:
                ax.legend(fontsize=8)
    fig.suptitle(f"real (red) vs synthetic (blue) s' at a fixed (s, a); {title}", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, name), dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=os.environ.get("OUT", "docs"))
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--num-data", type=int, default=4096)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--ema", type=float, nargs="+", default=[0.0, 0.995], help="EMA decays to compare (0 = off)")
    p.add_argument("--quick", action="store_true", help="300 steps (smoke run)")
    args = p.parse_args()
    run(300 if args.quick else args.steps, args.num_data, args.seed, args.out, tuple(args.ema), args.batch_size)
