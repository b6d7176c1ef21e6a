"""``make_method(name, env, student, config)``: every UED method by name, behind one interface.

Baselines live here (dr, plr, accel, accel-norevisit, paired); ``hmdp`` is the hierarchical DDPG
teacher of ``shed_jax.methods.hierarchical`` and ``shed`` that teacher plus a diffusion synthesiser
(``shed_jax.methods.shed``), imported lazily so the baselines work without the teacher's modules.

``config`` may be ``None`` (the method's defaults), the method's own config object, or a dict of
field overrides for it (e.g. ``{"updates_per_step": 2}``); unknown fields raise a ValueError that
names them and the method.
"""
from __future__ import annotations

import importlib
from typing import Any

from shed_jax.configs import coerce

# name -> (module, method class, config class)
_BASELINES: dict[str, tuple[str, str, str]] = {
    "dr": ("shed_jax.methods.dr", "DR", "DRConfig"),
    "plr": ("shed_jax.methods.plr", "PLR", "PLRConfig"),
    "accel": ("shed_jax.methods.accel", "ACCEL", "ACCELConfig"),
    "accel-norevisit": ("shed_jax.methods.accel", "ACCELNR", "ACCELNRConfig"),
    "paired": ("shed_jax.methods.paired", "PAIRED", "PAIREDConfig"),
}
# name -> (module, builder taking (env, student, config), config class)
_TEACHERS: dict[str, tuple[str, str, str]] = {
    "shed": ("shed_jax.methods.shed", "make_shed", "SHEDConfig"),
    "hmdp": ("shed_jax.methods.hierarchical", "make_hmdp", "HMDPConfig"),
    # the learning teacher of issue #26 (shed_jax.methods.learning_teacher): h-MDP's and SHED's versions
    "hmdp-x": ("shed_jax.methods.learning_teacher", "make_hmdp_x", "HMDPXConfig"),
    "shed-x": ("shed_jax.methods.learning_teacher", "make_shed_x", "SHEDXConfig"),
}
METHODS = tuple(_BASELINES) + tuple(_TEACHERS)


def config_class(name: str):
    """The config dataclass of method ``name``; None for an unknown name (``make_method`` reports it)."""
    entry = _TEACHERS.get(name) or _BASELINES.get(name)
    return None if entry is None else getattr(importlib.import_module(entry[0]), entry[2])


def make_method(name: str, env, student, config: Any = None):
    """The UED method ``name`` for ``env`` and ``student`` (see ``shed_jax.methods.base``)."""
    if name in _TEACHERS:
        module, builder, _ = _TEACHERS[name]
        return getattr(importlib.import_module(module), builder)(env, student, config)
    if name not in _BASELINES:
        raise ValueError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
    module, cls_name, cfg_name = _BASELINES[name]
    mod = importlib.import_module(module)
    return getattr(mod, cls_name)(env, student, coerce(getattr(mod, cfg_name), config, f"method {name!r}"))
