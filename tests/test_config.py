"""The typed run configuration: presets, JSON round trips, flags derived from the fields."""

from __future__ import annotations

import argparse
import dataclasses
import json

import pytest

from mjx_multiarm.options import (
    add_flags,
    apply,
    from_dict,
    leaves,
    option,
    overrides,
    to_dict,
    value_at,
)
from train import sac
from train.config import PRESETS, RunConfig


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_survive_json(name):
    preset = PRESETS[name]
    assert from_dict(RunConfig, json.loads(json.dumps(to_dict(preset)))) == preset


def test_every_field_is_a_flag_with_help():
    parser = argparse.ArgumentParser()
    add_flags(parser, RunConfig())
    flags = parser._option_string_actions
    for leaf in leaves(RunConfig):
        action = flags[f"--{leaf.path.replace('_', '-')}"]
        assert action.dest == leaf.path and action.help and "(default " in action.help, leaf.path


def test_flags_override_nested_fields_and_parse_their_types():
    args = sac._parser().parse_args(["--train.sac.gamma", "0.98", "--arms", "1-3", "--tolerance", "0.05,0.2", "--curriculum-by-team",
                                     "--no-curriculum", "--end-on-collision", "0", "--action-scale", "0.1", "--seed", "3"])
    config = sac.config_from_args(args)
    assert config.train.sac.gamma == 0.98 and config.data.arms == (1, 2, 3) and config.env.tolerance == (0.05, 0.2)
    assert config.train.curriculum_by_team and not config.train.curriculum and not config.env.end_on_collision
    assert config.env.action_scale == 0.1 and config.seed == 3
    untouched = {leaf.path for leaf in leaves(RunConfig)} - set(overrides(args, RunConfig))
    for path in untouched:
        assert value_at(config, path) == value_at(PRESETS["cpu"], path), path


def test_shortcuts_stand_for_their_settings():
    config = sac.config_from_args(sac._parser().parse_args(["--sac", "standard", "--observe", "self", "--collisions", "restore"]))
    assert config.train.sac.squash and config.train.sac.learn_alpha
    assert config.env.neighbour_radius == 0.0 and not config.env.end_on_collision


def test_bad_data_names_the_field():
    data = to_dict(RunConfig())
    data["train"]["sac"]["gama"] = 0.9
    with pytest.raises(ValueError, match=r"config.train.sac: unknown field\(s\) \['gama'\]"):
        from_dict(RunConfig, data)
    data = to_dict(RunConfig())
    data["budget"]["minutes"] = "ten"
    with pytest.raises(ValueError, match="config.budget.minutes: expected float"):
        from_dict(RunConfig, data)
    with pytest.raises(ValueError, match="unknown setting 'train.gama'"):
        apply(RunConfig(), {"train.gama": 0.9})
    with pytest.raises(ValueError, match="TrainConfig.num_envs must be >= 1"):
        apply(RunConfig(), {"train.num_envs": 0})


def test_checks_run_once_on_the_final_values():
    """Changes applied together are checked together: enabling the expert share while
    disabling behaviour cloning is fine although each change alone would not be."""
    bc = sac.config_from_args(sac._parser().parse_args(["--bc"]))
    changed = apply(bc, {"train.bc": False, "train.expert_share": 0.5})
    assert changed.train.expert_share == 0.5 and not changed.train.bc


@dataclasses.dataclass(frozen=True)
class _Section:
    width: int = option(3, "how wide")

    def __post_init__(self):
        if self.width < 1:
            raise ValueError("_Section.width must be >= 1")


@dataclasses.dataclass(frozen=True)
class _Config:
    section: _Section = _Section()


def test_a_new_option_is_one_field():
    """A field declared once with :func:`option` is a flag with help, JSON data and a check."""
    parser = argparse.ArgumentParser()
    add_flags(parser, _Config())
    args = parser.parse_args(["--width", "5"])
    assert "how wide" in parser.format_help()
    assert apply(_Config(), overrides(args, _Config)) == _Config(_Section(5))
    assert from_dict(_Config, to_dict(_Config(_Section(7)))).section.width == 7
    with pytest.raises(ValueError, match="width must be >= 1"):
        apply(_Config(), {"section.width": 0})


@pytest.mark.parametrize("flags, message", [
    (["--tasks", "x.npz", "--train-tasks", "5"], "--task-limit N takes the first N"),
    (["--task-limit", "5"], "first N >= 1 tasks of a --tasks file"),
    (["--experts", "x.experts"], "expert file of --tasks"),
    (["--tasks", "x.npz", "--layout", "original"], "--layout places generated tasks"),
])
def test_inconsistent_data_settings_are_rejected(flags, message):
    with pytest.raises(ValueError, match=message):
        sac.config_from_args(sac._parser().parse_args(flags))


def test_resume_changes_only_the_budget(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps(to_dict(PRESETS["tiny"])))
    resumed = sac.config_from_args(sac._parser().parse_args(["--resume", str(tmp_path), "--minutes", "3", "--eval-minutes", "1"]))
    assert resumed == apply(PRESETS["tiny"], {"budget.minutes": 3.0, "budget.eval_minutes": 1.0})
    for flags in (["--gamma", "0.5"], ["--no-expert"], ["--observe", "self"]):
        with pytest.raises(ValueError, match="only budget settings may change"):
            sac.config_from_args(sac._parser().parse_args(["--resume", str(tmp_path), *flags]))
