"""shed_jax.configs: one way to read, override and check every frozen config."""
import dataclasses
import json

import pytest

from shed_jax import configs
from shed_jax.methods.level_sampler import LevelSamplerConfig
from shed_jax.methods.plr import PLRConfig
from shed_jax.methods.registry import METHODS, config_class
from shed_jax.methods.shed import SHEDConfig
from shed_jax.student import PPOConfig, PPOHyperparams
from shed_jax.teacher.reward import RewardConfig


@pytest.mark.parametrize("method", METHODS)
def test_every_method_config_round_trips_through_json(method):
    cls = config_class(method)
    cfg = cls()
    back = configs.from_dict(cls, json.loads(json.dumps(configs.to_dict(cfg))))
    assert back == cfg and type(back) is cls


def test_the_json_form_is_strict_json_and_reads_back_unbounded_floats():
    import math
    cfg = PPOConfig()  # log-std bounds off by default: -inf and inf
    assert math.isinf(cfg.log_std_min) and math.isinf(cfg.log_std_max)
    text = json.dumps(configs.finite_json(configs.to_dict(cfg)), allow_nan=False)  # raises on Infinity/NaN
    saved = json.loads(text)
    assert saved["log_std_min"] == "-inf" and saved["log_std_max"] == "inf"
    assert configs.from_dict(PPOConfig, saved) == cfg
    # names stay strings for string fields, and non-finite values inside lists are named too
    assert configs.finite_json({"a": [1.0, float("nan"), -math.inf], "b": "inf", "c": (2, 3)}) == \
        {"a": [1.0, "nan", "-inf"], "b": "inf", "c": [2, 3]}
    # a config.json written before the names (json's -Infinity) still reads
    old = json.loads(json.dumps(configs.to_dict(cfg)))
    assert configs.from_dict(PPOConfig, old) == cfg


def test_a_saved_infinity_and_its_name_compare_equal_on_resume():
    from shed_jax.checkpoint import check_config, jsonable
    old = json.loads(json.dumps({"experiment": {"ppo": {"log_std_max": float("inf")}}}))  # an older config.json
    new = jsonable({"experiment": {"ppo": {"log_std_max": float("inf")}}})  # today's checkpoint meta
    assert new == {"experiment": {"ppo": {"log_std_max": "inf"}}}
    check_config(new, old, ["experiment"])  # no ConfigMismatchError


def test_from_dict_builds_nested_configs_and_keeps_defaults_for_missing_fields():
    cfg = configs.from_dict(SHEDConfig, {"psi": 0.5, "reward": {"eta": 10}, "low": [1, 2, 3]})
    assert cfg.reward == RewardConfig(eta=10) and cfg.psi == 0.5 and cfg.low == (1, 2, 3)
    assert cfg.num_levels == SHEDConfig().num_levels  # not in the dict: the default
    plr = configs.from_dict(PLRConfig, {"sampler": {"capacity": 4}})
    assert plr.sampler == LevelSamplerConfig(capacity=4)
    with pytest.raises(ValueError, match=r"sampler: LevelSamplerConfig has no field\(s\) 'cap'; known: capacity"):
        configs.from_dict(PLRConfig, {"sampler": {"cap": 4}})
    ppo = configs.from_dict(PPOConfig, configs.to_dict(PPOConfig.for_env("walker")))
    assert ppo == PPOConfig.for_env("walker") and isinstance(ppo.hparams, PPOHyperparams)


def test_with_overrides_merges_nested_configs_and_names_bad_fields():
    base = SHEDConfig(reward=RewardConfig(form="signed_sum"))
    cfg = configs.with_overrides(base, {"reward": {"eta": 3.0}, "num_levels": 4})
    assert cfg.reward == RewardConfig(form="signed_sum", eta=3.0) and cfg.num_levels == 4
    assert base.reward.eta == RewardConfig().eta  # the original is untouched
    assert configs.with_overrides(base, {}) is base
    with pytest.raises(ValueError, match=r"^--set: SHEDConfig has no field\(s\) 'bogus'; known: actor_lr"):
        configs.with_overrides(base, {"bogus": 1}, "--set ")
    with pytest.raises(ValueError, match=r'^--set psi: expected a number, got "x"$'):
        configs.with_overrides(base, {"psi": "x"}, "--set ")
    with pytest.raises(ValueError, match=r'^--set reward.eta: expected a number, got true$'):
        configs.with_overrides(base, {"reward": {"eta": True}}, "--set ")
    with pytest.raises(ValueError, match=r"^--set reward: expected a JSON object of RewardConfig fields, got 3$"):
        configs.with_overrides(base, {"reward": 3}, "--set ")
    with pytest.raises(ValueError, match="SHEDConfig.num_levels must be a positive int, got 0"):  # the class validates
        configs.with_overrides(base, {"num_levels": 0})


def test_literal_modes_are_checked_with_the_allowed_values():
    assert configs.modes(RewardConfig, "form") == ("paper_l1", "signed_sum", "code_mean")
    with pytest.raises(ValueError, match=r"^RewardConfig.form must be one of 'paper_l1', 'signed_sum', 'code_mean', got 'l2'$"):
        RewardConfig(form="l2")
    with pytest.raises(ValueError, match=r"^SHEDConfig.syn_action must be one of 'uniform', 'bc', 'policy', got 'x'$"):
        SHEDConfig(syn_action="x")
    with pytest.raises(ValueError, match=r"^PPOConfig.activation must be one of 'tanh', 'relu'"):
        PPOConfig(activation="sigmoid")
    # every config class with a Literal field refuses a value outside it
    for method in METHODS:
        cls = config_class(method)
        for name in configs._modes(cls):
            with pytest.raises(ValueError, match=f"{cls.__name__}.{name} must be one of"):
                cls(**{name: "not-a-mode"})


def test_coerce_takes_none_a_dict_or_the_class_only():
    assert configs.coerce(SHEDConfig, None, "method 'shed'") == SHEDConfig()
    assert configs.coerce(SHEDConfig, {"psi": 0.5}, "method 'shed'") == SHEDConfig(psi=0.5)
    cfg = SHEDConfig(psi=0.25)
    assert configs.coerce(SHEDConfig, cfg, "method 'shed'") is cfg
    with pytest.raises(TypeError, match="method 'plr': config must be None, a dict or a PLRConfig, got ACCELConfig"):
        configs.coerce(PLRConfig, config_class("accel")(), "method 'plr'")
    with pytest.raises(ValueError, match=r"'eta' is a field of 'reward', given inside it"):
        configs.coerce(SHEDConfig, {"eta": 1}, "method 'shed'")
    assert dataclasses.is_dataclass(configs.coerce(PLRConfig, {"sampler": {"capacity": 8}}, "x").sampler)


def test_a_saved_run_from_before_level_switch_resumes_in_the_mode_it_ran():
    """Whole episodes became the native methods' default after runs had been saved without the field:
    such a run rebuilds with level_switch='rollout' (SAVED_BEFORE), a run that saved it keeps it."""
    from shed_jax.experiment import experiment_from_dict
    from shed_jax.presets import build_experiment

    for method in ("dr", "plr", "accel", "paired"):
        saved = build_experiment("lander", method, "quick").to_dict()
        assert saved["method_config"]["level_switch"] == "episode"  # today's default
        assert experiment_from_dict(saved).method_config.level_switch == "episode"
        del saved["method_config"]["level_switch"]
        assert experiment_from_dict(saved).method_config.level_switch == "rollout"
    hm = build_experiment("lander", "hmdp", "quick").to_dict()  # no such field, nothing added
    assert "level_switch" not in experiment_from_dict(hm).to_dict()["method_config"]


def test_check_number_bounds_finiteness_and_message():
    import dataclasses as dc

    @dc.dataclass(frozen=True)
    class C:
        x: float = 1.0

    configs.check_number(C(0.0), "x", at_least=0)  # the bound itself passes >=
    configs.check_number(C(float("inf")), "x", above=0, finite=False)
    for value, kw, rule in ((0.0, dict(above=0), "finite number > 0"), (-1e-9, dict(at_least=0), "finite number >= 0"),
                            (float("inf"), dict(above=0), "finite number > 0"), (float("nan"), dict(above=0, finite=False), "number > 0"),
                            ("1", dict(at_least=0), "finite number >= 0")):
        with pytest.raises(ValueError, match=rf"^C\.x must be a {rule}, got {value!r}$".replace("(", r"\(").replace(")", r"\)")):
            configs.check_number(C(value), "x", **kw)

