"""SHED teacher parts: reward, replay buffers, DDPG, the DDPG teacher, conditional diffusion model, synthesiser."""
from shed_jax.teacher.buffers import (
    RingBuffer,
    Transition,
    buffer_add,
    buffer_add_many,
    buffer_init,
    buffer_sample,
    make_transition,
    num_real_in_batch,
    sample_mixed,
)
from shed_jax.teacher.ddpg import (
    DDPG,
    DDPGConfig,
    DDPGState,
    ddpg_act,
    ddpg_init,
    ddpg_update,
    make_ddpg,
    with_learning_rates,
)
from shed_jax.teacher.ddpg_teacher import DDPGTeacher
from shed_jax.teacher.diffusion import (
    DiffusionConfig,
    DiffusionModel,
    DiffusionState,
    make_diffusion,
    vp_schedule,
)
from shed_jax.teacher.reward import RewardConfig, coefficient_of_variation, make_reward_fn, teacher_reward, zscore, zscore_mixed
from shed_jax.teacher.synthesiser import DiffusionSynthesiser, SynthState
