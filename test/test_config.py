"""StereoConfig checks every value when it is made; the node's parameter ranges are its own."""
import argparse
import dataclasses
import re

from gcp_stereo_ros.ros.params import BY_NAME, coerce, config_from_params, PARAMS
from gcp_stereo_ros.stereo.config import (CHOICES, FLAGS, number_text, PRESETS, range_text,
                                          RANGES, StereoConfig)
from gcp_stereo_ros.stereo.costs import COSTS
from gcp_stereo_ros.stereo.pipeline import StereoResult
from gcp_stereo_ros.tools import evaluate
import numpy as np
import pytest

# Values that let a field reach an end of its range (p1 at its top needs p2 there too).
PARTNERS = {('p1', 'high'): {'p2': RANGES['p2'][1]}, ('p2', 'low'): {'p1': 0.0},
            ('c_low', 'high'): {'c_hi': RANGES['c_hi'][1]}, ('c_hi', 'low'): {'c_low': 0.0}}


def test_a_bad_config_is_refused_when_made_naming_each_field_and_its_range():
    with pytest.raises(ValueError) as err:
        StereoConfig(theta=-1, paths=5)
    assert str(err.value) == ('paths must be one of 4, 8, 16, got 5; '
                              'theta must be a number in [0, 1], got -1')


@pytest.mark.parametrize('name', sorted(RANGES))
def test_each_number_field_takes_both_ends_of_its_range_and_nothing_beyond(name):
    low, high = RANGES[name]
    integer = isinstance(low, int)
    for end, value in (('low', low), ('high', high)):
        config = StereoConfig(**{name: value, **PARTNERS.get((name, end), {})})
        assert getattr(config, name) == value
    below, above = (low - 1, high + 1) if integer else (low - 1e-3 * (high - low) or -1e-6,
                                                        high + 1e-3 * (high - low))
    kind = 'an integer' if integer else 'a number'
    for value in (below, above):
        want = f'{name} must be {kind} in {range_text(low, high)}, got {value!r}'
        with pytest.raises(ValueError, match=re.escape(want)):
            StereoConfig(**{name: value})


@pytest.mark.parametrize('name, value', [
    ('max_disp', 64.0), ('max_disp', True), ('speckle_size', 10.5), ('memory_limit_mb', '512'),
    ('theta', float('nan')), ('p2', float('inf')), ('min_confidence', False), ('p1', '8'),
])
def test_a_number_of_the_wrong_kind_is_refused(name, value):
    with pytest.raises(ValueError, match=f'^{name} must be '):
        StereoConfig(**{name: value})


@pytest.mark.parametrize('name', FLAGS)
def test_a_flag_must_be_a_boolean(name):
    with pytest.raises(ValueError, match=f"^{name} must be true or false, got 'no'$"):
        StereoConfig(**{name: 'no'})
    assert getattr(StereoConfig(**{name: np.bool_(True)}), name)


@pytest.mark.parametrize('name', sorted(CHOICES))
def test_a_choice_field_takes_only_its_choices(name):
    for choice in CHOICES[name]:
        assert getattr(StereoConfig(**{name: choice}), name) == choice
    wrong = {'cost': 'ncc', 'paths': 16.0, 'downsample': 3, 'precision': 'fp16'}[name]
    with pytest.raises(ValueError, match=f'^{name} must be one of '):
        StereoConfig(**{name: wrong})


@pytest.mark.parametrize('changes, message', [
    ({'p1': 200.0}, r'P2 \(128\.0\) must be >= P1 \(200\.0\)'),
    ({'c_low': 300.0}, r'c_low \(300\.0\) must be <= c_hi \(200\.0\)'),
    ({'min_depth': 5.0, 'max_depth': 2.0}, r'max_depth \(2\.0\) must be above min_depth'),
    ({'cost': 'census', 'window': 13}, r'census window must be an odd integer in \[3, 11\]'),
    ({'cost': 'sad', 'window': 8}, r'sad window must be an odd integer in \[3, 31\]'),
    ({'device': 'gpu'}, r"device must be 'cpu' or 'cuda\[:N\]', got 'gpu'"),
    ({'weights': None}, r'weights must be a file path'),
])
def test_relations_windows_devices_and_paths_are_checked(changes, message):
    with pytest.raises(ValueError, match=message):
        StereoConfig(**changes)


def test_a_relation_is_not_said_of_a_value_already_refused():
    with pytest.raises(ValueError) as err:
        StereoConfig(p1=-5.0)
    assert str(err.value) == 'p1 must be a number in [0, 10000], got -5.0'


def test_presets_and_replace_still_work_and_are_checked():
    for preset, fields in PRESETS.items():
        for cost, spec in COSTS.items():
            if preset not in spec.presets:
                with pytest.raises(ValueError, match=f"preset '{preset}' has no values for "
                                   f"cost '{cost}'"):
                    StereoConfig.for_cost(cost, preset)
                continue
            config = StereoConfig.for_cost(cost, preset, max_disp=64)
            values = {**spec.presets['default'], **spec.presets[preset], **fields}
            assert {k: getattr(config, k) for k in values} == values
            assert (config.cost, config.max_disp) == (cost, 64)
    assert 'sad' in COSTS and 'realtime' not in COSTS['sad'].presets  # the refusal ran
    config = StereoConfig()
    assert dataclasses.replace(config, paths=8).paths == config.replace(paths=8).paths == 8
    with pytest.raises(ValueError, match='theta must be a number in'):
        dataclasses.replace(config, theta=1.5)
    with pytest.raises(ValueError, match='paths must be one of'):
        config.replace(paths=5)
    with pytest.raises(ValueError, match=r'^sad window must be an odd integer in \[3, 31\]'):
        StereoConfig.for_cost('sad', window=33)


def test_the_node_parameters_take_their_ranges_and_choices_from_the_config():
    fields = {p.field for p in PARAMS if p.field}
    assert fields == set(StereoConfig.__dataclass_fields__)  # every field is a parameter
    for p in PARAMS:
        if p.field == 'window':
            assert p.range == (*COSTS[p.cost].windows, 2), p.name
        elif p.field in RANGES:
            low, high = RANGES[p.field]
            assert p.range == (low, high, 1 if isinstance(low, int) else 0.0), p.name
            assert type(p.default) is type(low), p.name  # the descriptor's kind is the field's
        elif p.field in CHOICES:
            assert p.choices == tuple(CHOICES[p.field]), p.name


@pytest.mark.parametrize('name', [p.name for p in PARAMS if p.field and p.range])
def test_a_node_parameter_outside_its_range_is_refused_with_its_ros_name(name):
    low, high, step = BY_NAME[name].range
    assert coerce(name, high) == high
    with pytest.raises(ValueError, match=re.escape(f'{name} must be in {range_text(low, high)}')):
        config_from_params({name: high + (step or 1)})


def test_config_from_params_names_the_cost_of_a_crossed_pair():
    with pytest.raises(ValueError, match=r'^census: P2 \(128\.0\) must be >= P1 \(300\.0\)'):
        config_from_params({'census.P1': 300.0})


@pytest.mark.parametrize('argv, reason', [
    (['--set', 'theta=-1', '--methods', 'census+gcp'],
     'census+gcp with --preset default --set theta=-1: theta must be a number in [0, 1], got -1'),
    (['--preset', 'paper', '--set', 'window=13', '--methods', 'sad', 'cnn'],
     'cnn with --preset paper --set window=13: census window must be an odd integer in [3, 11], '
     'got 13'),
    (['--set', 'max_disp=64'], "--set 'max_disp=64': max_disp is set by --max-disp"),
    (['--set', 'use_gcp=false'], "--set 'use_gcp=false': use_gcp is set by --methods"),
])
def test_eval_refuses_bad_settings_before_any_frame(capsys, argv, reason):
    assert evaluate.main(['--dataset', 'motorcycle', *argv]) == 1
    assert capsys.readouterr().err.strip() == f'gcp-stereo-eval: error: {reason}'


def test_eval_checks_each_method_with_its_own_cost():
    args = argparse.Namespace(paths=16, set=['window=13'], preset='default', methods=['sad'],
                              max_disp=None)
    assert evaluate.make_runner(args).config('sad', 64).window == 13  # census would refuse it


def documented_fields(cls):
    """Return {name: text} of the Attributes section of `cls`'s docstring."""
    section = cls.__doc__.split('Attributes\n    ----------\n', 1)[1]
    parts = re.split(r'^    (\w+) : .*$', section, flags=re.M)[1:]
    return {name: ' '.join(text.split()) for name, text in zip(parts[::2], parts[1::2])}


def test_every_field_is_documented_with_its_range_or_choices():
    docs = documented_fields(StereoConfig)
    assert list(docs) == list(StereoConfig.__dataclass_fields__)  # each, in order
    for name, (low, high) in RANGES.items():
        assert f'in {range_text(low, high)}' in docs[name], name
    for cost, spec in COSTS.items():
        assert f'{cost} in [{spec.windows[0]}, {spec.windows[1]}]' in docs['window']
    for name, choices in CHOICES.items():
        assert all(repr(c).strip("'") in docs[name] for c in choices), name


def _text(value):
    """Return a default as the docstring writes it: 12.0 as 12, 'census' as 'census'."""
    return repr(value) if isinstance(value, (bool, str)) else number_text(value)


def test_every_field_is_documented_with_its_default_or_each_cost_s():
    docs = documented_fields(StereoConfig)
    for field in dataclasses.fields(StereoConfig):
        per_cost = {cost: spec.presets['default'].get(field.name) for cost, spec in COSTS.items()}
        if field.name in COSTS['census'].presets['default'] and len(set(per_cost.values())) > 1:
            for cost, value in per_cost.items():
                assert f'{cost} {_text(value)}' in docs[field.name], (field.name, cost)
        else:
            assert docs[field.name].endswith(f'default {_text(field.default)}.'), field.name


def test_every_result_field_is_documented():
    docs = documented_fields(StereoResult)
    assert list(docs) == list(StereoResult.__dataclass_fields__)
    assert all(('(H, W)' in text) != (name == 'seconds') for name, text in docs.items())
