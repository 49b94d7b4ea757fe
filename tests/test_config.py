"""``config.assemble``: the config of one ``usp-jax train`` command, from its preset or file, data
source, initial weights, overrides and step count."""

import pytest

from usp_jax import config as config_lib


def test_steps_and_num_steps_override_must_agree():
    with pytest.raises(ValueError, match="--steps 2 and num_steps=3 disagree; give one of them"):
        config_lib.assemble("cpu", overrides=["num_steps=3"], steps=2)
    # The last num_steps= counts, as it is the one the overrides leave in force.
    with pytest.raises(ValueError, match="--steps 2 and num_steps=5 disagree"):
        config_lib.assemble("cpu", overrides=["num_steps=2", "num_steps=5"], steps=2)
    agreed = config_lib.assemble("cpu", overrides=[" num_steps = 7"], steps=7)
    assert agreed.num_steps == 7


def test_steps_alone_sets_num_steps_and_without_it_the_preset_or_override_stands():
    assert config_lib.assemble("cpu", steps=9).num_steps == 9
    assert config_lib.assemble("cpu").num_steps == config_lib.cpu().num_steps
    assert config_lib.assemble("cpu", overrides=["num_steps=11"]).num_steps == 11


def test_a_bad_num_steps_override_is_refused_before_it_is_compared_with_steps():
    with pytest.raises(ValueError, match="num_steps=-1 must be >= 1"):
        config_lib.assemble("cpu", overrides=["num_steps=-1"], steps=2)


def test_data_and_init_apply_before_the_overrides_which_win_over_them():
    overrides = ["seed=3"]
    config = config_lib.assemble(
        "paper", data="sample", init="start.npz", overrides=overrides, steps=4
    )
    assert (config.data.source, config.init_weights, config.seed) == ("sample", "start.npz", 3)
    assert overrides == ["seed=3"]  # the caller's list is left as it was
    explicit = config_lib.assemble("paper", data="sample", overrides=["data.source=tfds:coco"])
    assert explicit.data.source == "tfds:coco"


def test_no_data_or_init_keeps_the_presets():
    assert config_lib.assemble("paper") == config_lib.paper()
    assert config_lib.assemble("paper", data="", init="") == config_lib.paper()
