"""``python -m shed_jax run``: one UED method on one environment, seeds vmapped, end to end.

This module is the command's flags; ``shed_jax.driver.run`` does the work. The compiled loop runs in
chunks of budget steps; after each, the host checks it for non-finite values, writes the per-step
metrics (``metrics.jsonl``), saves a checkpoint of the whole run state (``DIR/checkpoints/<step>``,
the last ``--keep``), prints a one-line summary and updates a progress bar. At the end it writes
plots, the final evaluations and ``summary.json`` (last).

Every flag is checked before the run directory is made: a mistake is one line on stderr and exit
code 2 (``shed_jax/cli/errors.py``), and leaves nothing behind. ``--resume DIR`` continues a run
from its latest checkpoint (or ``--from-step N``), bitwise as if it had not stopped; ``--out DIR
--restart`` starts over a run that never saved a checkpoint. SIGINT/SIGTERM finish the current
chunk, save and exit with 130/143 (during start-up: at once, keeping nothing); ``--stop-after`` and
``--time-limit`` stop the same way with exit code 75. See docs/running.md.
"""
from __future__ import annotations

from shed_jax.cli import errors
from shed_jax.errors import EXIT_CHECKPOINT
from shed_jax.experiment import DEFAULT_ENV, DEFAULT_METHOD, DEFAULT_ROOT_SEED, ENVS
from shed_jax.rundir import DISCARDED_DIR


def add_arguments(p) -> None:
    from shed_jax.methods.registry import METHODS
    from shed_jax.presets import PRESETS

    count = errors.positive_int
    p.add_argument("--env", default=None, choices=ENVS, help=f"{' | '.join(ENVS)} (default {DEFAULT_ENV})")
    p.add_argument("--method", default=None, choices=METHODS,
                   help=f"{' | '.join(METHODS)} (default {DEFAULT_METHOD})")
    p.add_argument("--preset", default=None, choices=("auto",) + PRESETS,
                   help="auto (default): 'paper' on a GPU, 'quick' on a CPU (the choice is printed); dcd: DCD's walker budget, "
                        "6.6e8 student steps per seed (walker and bipedal)")
    p.add_argument("--seeds", type=count, default=None, help="number of vmapped seeds (default: quick 2, paper and dcd 5)")
    p.add_argument("--seed", type=int, default=None,
                   help=f"root seed (default {DEFAULT_ROOT_SEED}); seed i of the batch uses fold_in(root, i)")
    p.add_argument("--episodes", type=count, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=count, default=None, help="override the budget steps per episode T")
    p.add_argument("--test-episode-every", type=count, default=None, metavar="K",
                   help="run the test set only in teacher episodes 0, K, 2K, ... and the last "
                        "(default: paper preset 10 for shed/hmdp, else 1 = every episode)")
    p.add_argument("--chunk", type=count, default=None,
                   help="budget steps per compiled call, i.e. between checkpoints (default: T)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the method's config (repeatable), e.g. --set num_eval_levels=20; "
                        "SHED/h-MDP: a field of the teacher reward goes into its 'reward' config, e.g. --set eta=10 "
                        "or --set form=signed_sum")
    p.add_argument("--ppo", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the student's PPOConfig or PPOHyperparams (repeatable), "
                        "e.g. --ppo num_envs=8 --ppo num_steps=640")
    p.add_argument("--out", default=None, help="run directory (default runs/<env>-<method>-<preset>-<time>)")
    p.add_argument("--no-gif", action="store_true", default=None,
                   help="skip the GIF of the final student (saved with the run: --resume keeps it)")
    p.add_argument("--final-eval", default=None, metavar="LEVELS",
                   help="after the last budget step, evaluate the final students on level sets as `eval --levels` "
                        "does (test | named | FILE.json, comma-separated, or none) and write final_eval_<set>.json; "
                        "default: the env's own choice (its UEDSpec.final_eval): named on walker and bipedal, none elsewhere; "
                        "saved with the run: --resume keeps it")
    p.add_argument("--final-eval-episodes", type=count, default=None, metavar="N",
                   help="episodes per level and seed of --final-eval (default 10; saved with the run: --resume keeps it); "
                        "the episode cap is the test set's")
    p.add_argument("--compile-final-eval", choices=("auto", "early", "late"), default="auto",
                   help="when --final-eval's program compiles: early (in a worker thread while training runs, from "
                        "the first chunk on), late (after training), or auto: early on a GPU, where the host is "
                        "idle meanwhile, late on a CPU (default auto)")
    g = p.add_argument_group("checkpoints and stopping")
    g.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the run in DIR from its latest checkpoint (its saved configuration is used; "
                        "experiment flags given as well must agree with it)")
    g.add_argument("--from-step", type=count, default=None, metavar="N",
                   help="with --resume: continue from checkpoint N instead of the latest (e.g. when the latest is "
                        f"damaged); the newer ones are moved to DIR/{DISCARDED_DIR}/")
    g.add_argument("--restart", action="store_true",
                   help="with --out DIR: clear a run in DIR that stopped before its first checkpoint and start it "
                        "over (refused when DIR holds a checkpoint or a finished run)")
    g.add_argument("--keep", type=count, default=None, metavar="K",
                   help="keep the last K checkpoints (default 3; saved with the run, so --resume keeps it unless given again)")
    g.add_argument("--no-checkpoint", action="store_true", help="do not save checkpoints (the run cannot be resumed)")
    g.add_argument("--checkpoint-every", type=errors.non_negative_float, default=None, metavar="SECONDS",
                   help="save a checkpoint at most this often (default 0: after every chunk; saved with the run like "
                        "--keep); the last chunk and a stop always save. For states of gigabytes (SHED sweeps of "
                        "hundreds of seeds)")
    g.add_argument("--stop-after", type=count, default=None, metavar="STEPS",
                   help="stop at the first chunk boundary at or after this many budget steps, save, exit 75")
    g.add_argument("--time-limit", type=errors.non_negative_float, default=None, metavar="SECONDS",
                   help="stop at the first chunk boundary after this much wall time in this process, save, exit 75")
    g.add_argument("--profile-chunk", type=count, default=None, metavar="K",
                   help="run this process's K-th chunk under jax.profiler and write where its time went (busy vs idle, "
                        "time by op, loop and named scope) to DIR/profile_chunkK.json; 2 is the first chunk with "
                        "nothing left to compile")


def main(args) -> int:
    from shed_jax import driver
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.errors import WriteFailedError

    try:
        return driver.run(driver.RunOptions.from_args(args))
    except CheckpointError as err:
        errors.report(err, args)
        return EXIT_CHECKPOINT
    except WriteFailedError as err:  # one line naming what is safe on disk
        errors.report(err, args)
        return err.code
