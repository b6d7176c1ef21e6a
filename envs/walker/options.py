"""Static (compile-time) options of the walker: physics, solver and terrain resolution knobs."""
from __future__ import annotations

import dataclasses

from envs.physics2d.fused import MODES as KERNELS

PRECISIONS = ("highest", "high", "default")  # jax.default_matmul_precision names for float32


@dataclasses.dataclass(frozen=True)
class WalkerOptions:
    """Validated static configuration; everything here changes compiled shapes or the model.

    substeps:            physics steps per 0.02 s control step (timestep = 0.02 / substeps).
    solver_iterations:   Newton iterations per physics step (4: converged, see docs/walker.md).
    ls_iterations:       line-search iterations per Newton iteration.
    terrain_resolution:  heightfield samples per TERRAIN_STEP (0.4667 m); faces are 1 sample wide.
    kv:                  velocity-servo gain of the motor (N m per rad/s), see docs/walker.md.
    collide_upper_legs:  also collide the thighs with the ground. Box2D does; off by default because the
                         two extra heightfield pairs cost 39 % of the step at 32k envs on an H200
                         (docs/log/benchmarks.md "Knob sweep and the new default") and a thigh reaches the ground only in a deep kneel.
    max_boxes:           obstacle box slots per level (extra boxes are dropped; 64 covers FULL).
    terrain_unroll:      columns per iteration of the terrain generator's 200-column loop (speed
                         only: the same terrain up to float32 rounding). Every auto-reset generates a terrain, so on a GPU
                         the loop's 200 dependent iterations are part of every training step.
    terrain_kernel:      the terrain loop's ``envs.physics2d.fused`` mode: "auto" runs it as one GPU
                         kernel on GPUs (the XLA loop elsewhere); speed only, the same terrain up to rounding.
    z_span:              vertical extent of the heightfield above its per-level base (m).
    contact_threshold:   a lower leg touches the ground if a contact's distance is <= this (m).
    unroll_substeps:     unroll the substep loop in Python (faster on GPU) instead of lax.scan.
    matmul_precision:    float32 matmul precision of the MJX physics. "highest" (the default) keeps
                         it float32 on GPUs; "high" allows TF32-like multi-pass modes where the
                         backend has them; "default" lets recent NVIDIA GPUs use TF32 (10 mantissa
                         bits), which changed observations on the first step of a batch by up to
                         1.0 and saved 2.8 % of a step at 32k envs on an H200 (docs/walker.md).
                         CPUs are float32 either way.
    """

    substeps: int = 5
    solver_iterations: int = 4
    ls_iterations: int = 5
    terrain_resolution: int = 4
    kv: float = 20.0
    collide_upper_legs: bool = False
    max_boxes: int = 64
    terrain_unroll: int = 1
    terrain_kernel: str = "auto"
    z_span: float = 100.0
    contact_threshold: float = 0.01
    unroll_substeps: bool = False
    matmul_precision: str = "highest"

    def __post_init__(self):
        ints = dict(substeps=(1, 50), solver_iterations=(1, 100), ls_iterations=(0, 100), terrain_resolution=(1, 32), max_boxes=(8, 512),
                    terrain_unroll=(1, 200))
        for name, (lo, hi) in ints.items():
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise ValueError(f"WalkerOptions.{name} must be an int in [{lo}, {hi}], got {v!r}")
        for name in ("kv", "z_span", "contact_threshold"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"WalkerOptions.{name} must be a positive number, got {v!r}")
        for name in ("collide_upper_legs", "unroll_substeps"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"WalkerOptions.{name} must be a bool, got {getattr(self, name)!r}")

        if self.terrain_kernel not in KERNELS:
            raise ValueError(f"WalkerOptions.terrain_kernel must be one of {KERNELS}, got {self.terrain_kernel!r}")
        if self.matmul_precision not in PRECISIONS:
            raise ValueError(f"WalkerOptions.matmul_precision must be one of {PRECISIONS}, got {self.matmul_precision!r}")

    @property
    def timestep(self) -> float:
        return 0.02 / self.substeps
