"""``python -m shed_jax sweep``: seeds x hyperparameter grid x methods, one compile per shape group.

    python -m shed_jax sweep --env lander --methods shed,hmdp --preset quick --seeds 2 \\
        --grid eta=0,10 --grid actor_lr=1e-3,3e-4 --out runs/sweep-eta-lr

This module is the command's flags; ``shed_jax.sweep`` plans the groups (which grid keys are
dynamic or static for each method) and runs each through ``shed_jax.driver`` as ``run``
runs one: the same compile lines, checkpoints, non-finite guard, signals and failed-write reports.
See docs/sweeps.md.
"""
from __future__ import annotations

from shed_jax.experiment import ENVS


def add_arguments(p) -> None:
    from shed_jax.cli.errors import non_negative_float, positive_int
    from shed_jax.presets import PRESETS

    count = positive_int
    p.add_argument("--env", default="lander", choices=ENVS, help=" | ".join(ENVS))
    p.add_argument("--methods", default="shed", help="comma-separated: shed,hmdp,dr,paired,accel,accel-norevisit,plr")
    p.add_argument("--preset", default="auto", choices=("auto",) + PRESETS,
                   help="auto: 'paper' on a GPU, 'quick' on a CPU (the choice is printed); dcd: DCD's walker budget, "
                        "6.6e8 student steps per seed (walker and bipedal)")
    p.add_argument("--seeds", type=count, default=None, help="seeds per grid point (default: quick 2, paper 5)")
    p.add_argument("--seed", type=int, default=0, help="root seed; seed i uses fold_in(root, i) at every point")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a grid axis (repeatable); values are JSON or strings, e.g. --grid eta=0,10 --grid ppo.lr=1e-4,3e-4")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="fix a key for every point (repeatable), e.g. --set num_eval_levels=20")
    p.add_argument("--episodes", type=count, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=count, default=None, help="override the budget steps per episode T")
    p.add_argument("--test-episode-every", type=count, default=None, metavar="K",
                   help="as for run: the test set runs only in teacher episodes 0, K, 2K, ... and the last "
                        "(default: paper preset 10 for shed/hmdp, else 1 = every episode)")
    p.add_argument("--chunk", type=count, default=None, help="budget steps per compiled call (default: T)")
    p.add_argument("--devices", type=count, default=None, help="use the first N visible devices (default: all)")
    p.add_argument("--no-pad", action="store_true",
                   help="refuse (error) when a group's seeds x points does not divide by the device count, instead of padding")
    p.add_argument("--no-plots", action="store_true", help="skip the per-point plots")
    p.add_argument("--final-eval", default=None, metavar="LEVELS",
                   help="as for run: after the last budget step, evaluate every point's final students on level sets "
                        "(test | named | FILE.json, comma-separated, or none) into <point>/final_eval_<set>.json; "
                        "default: walker named, other envs none")
    p.add_argument("--final-eval-episodes", type=count, default=10, metavar="N",
                   help="episodes per level and seed of --final-eval (default 10)")
    p.add_argument("--out", default=None, help="sweep directory (default runs/sweep-<env>-<preset>-<time>)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the sweep in DIR with its saved arguments: finished groups are kept, the "
                        "group in progress continues from its last checkpoint (other arguments are ignored, except "
                        "--time-limit and --checkpoint-every)")
    p.add_argument("--time-limit", type=non_negative_float, default=None, metavar="SECONDS",
                   help="after the chunk in which this many seconds have passed, save and stop (exit code 75); "
                        "continue with --resume")
    p.add_argument("--checkpoint-every", type=non_negative_float, default=0.0, metavar="SECONDS",
                   help="checkpoint the group in progress at most this often (default 0: after every chunk); its "
                        "last chunk and a stop always save. A SHED state is about 9.4 MB per seed")
    p.add_argument("--no-checkpoint", action="store_true",
                   help="do not checkpoint the group in progress (the sweep cannot be resumed)")



def main(args) -> int:
    from shed_jax import sweep
    from shed_jax.cli import errors
    from shed_jax.errors import WriteFailedError

    try:
        return sweep.sweep(sweep.SweepOptions.from_args(args))
    except WriteFailedError as err:  # one line naming what is safe on disk
        errors.report(err, args)
        return err.code
