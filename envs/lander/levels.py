"""The lander's UED data (``LunarLander.ued``): teacher box Θ, training time limit, ACCEL's edit
table, the official code's DR, and the evaluation, test and named level sets.

The level sets' data (the official code's tables and generators) lives in ``shed_jax.eval_sets``
with the other environments' sets; the builders here import it when called, so importing the
environment does not import the UED code.
"""
from __future__ import annotations

from envs.core import FIXED, EditTable, UEDSpec

# docs/design.md §5: the teacher box Θ over (gravity, wind_power, turbulence_power).
THETA_LOW = (-9.0, 0.01, 0.01)
THETA_HIGH = (-0.01, 12.0, 1.5)
# docs/design.md §13.1: training levels run 600 steps, evaluation and test levels 500 [official code].
TRAIN_MAX_STEPS = 600

# docs/design.md §8.5: edit steps 4 % of Θ's width, clipped to Θ; EASY g ~ U[-7, -3], wind ~ U[0.01, 1],
# turbulence ~ U[0.01, 0.1] [our choice].
EDIT_TABLE = EditTable(
    steps=(0.36, 0.48, 0.06),
    kinds=(FIXED, FIXED, FIXED),
    easy_low=(-7.0, 0.01, 0.01),
    easy_high=(-3.0, 1.0, 0.1),
)

# docs/design.md §8.2 `dr=code` [official code]: (mean, std, clip low, clip high) per parameter; the
# wind is switched on with probability 0.5.
CODE_DR = ((-10.0, 1.0, -11.99, -0.01), (15.0, 1.0, 0.01, 19.99), (1.5, 0.5, 0.01, 1.99))


def eval_set(kind: str, m: int):
    """The teacher's evaluation set: ``"official"`` (the official code's landers) or else the
    paper's covering construction (docs/design.md §9.1)."""
    from shed_jax import eval_sets

    return eval_sets.official_lander_eval_set(m) if kind == "official" else eval_sets.lander_paper_eval_set(m)


def test_levels(base):
    """The official 10 test landers (docs/design.md §9.2), labelled test-i."""
    from shed_jax import eval_sets

    ls = eval_sets.lander_test_set()
    return ls.to_params(base), [f"test-{i}" for i in range(len(ls))]


def named_levels(base):
    """The official 10 evaluation landers (eval-i) then the 10 test landers (test-i)."""
    from shed_jax import eval_sets

    ev, te = eval_sets.official_lander_eval_set(), eval_sets.lander_test_set()
    labels = [f"eval-{i}" for i in range(len(ev))] + [f"test-{i}" for i in range(len(te))]
    return eval_sets.concat_sets([ev, te]).to_params(base), labels


UED = UEDSpec(
    theta_low=THETA_LOW,
    theta_high=THETA_HIGH,
    train_max_steps=TRAIN_MAX_STEPS,
    train_fields=(("enable_wind", True),),  # docs/design.md §5: every generated level has wind
    edit_table=EDIT_TABLE,
    code_dr=CODE_DR,
    eval_set=eval_set,
    test_sets=(("lander-test", test_levels),),
    named_levels=named_levels,
    solved_threshold=200.0,  # docs/design.md §9.3 [ours, Gymnasium's threshold]
)
