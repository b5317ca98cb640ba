"""Parameter files as the node and `gcp-stereo-bag run --params` read them, ROS-free."""
from pathlib import Path

from gcp_stereo_ros.ros.params import config_from_params, load_params_file
from gcp_stereo_ros.stereo.config import StereoConfig
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path, doc):
    path = tmp_path / 'params.yaml'
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return path


def test_shipped_files_apply_to_any_node_name_and_hold_both_costs():
    for name, preset in (('gcp_stereo.yaml', 'default'), ('gcp_stereo_paper.yaml', 'paper')):
        doc = yaml.safe_load((REPO / 'config' / name).read_text())
        assert list(doc) == ['/**'], name  # any name, any namespace: rcl's wildcard
        values = load_params_file(REPO / 'config' / name)
        for cost in ('census', 'sad'):
            assert (config_from_params({**values, 'cost': cost})
                    == StereoConfig.for_cost(cost, preset)), (name, cost)


def test_a_ros2_param_dump_file_is_read(tmp_path):
    """What `ros2 param dump /stereo/gcp_stereo_node` prints: a namespaced key, nested names."""
    path = write(tmp_path, {'/stereo/gcp_stereo_node': {'ros__parameters': {
        'cost': 'sad', 'census': {'P2': 64.0}, 'sad': {'P1': 2, 'P2': 14.0},
        'qos_overrides': {'/stereo/left/image_rect': {'subscription': {'depth': 1}}},
        'start_type_description_service': True, 'use_sim_time': False}}})
    values = load_params_file(path)
    assert values == {'cost': 'sad', 'census.P2': 64.0, 'sad.P1': 2.0, 'sad.P2': 14.0}
    assert type(values['sad.P1']) is float  # a whole number for a decimal parameter
    config = config_from_params(values)
    assert (config.cost, config.p1, config.p2) == ('sad', 2.0, 14.0)


def test_entries_for_the_node_and_wildcards_merge_as_rcl_does(tmp_path):
    path = write(tmp_path, {
        'other_node': {'ros__parameters': {'sad.window': 3}},
        '/**/gcp_stereo_node': {'ros__parameters': {'sad.window': 7}},
        '/**': {'ros__parameters': {'sad.window': 5, 'median': True}},
    })
    assert load_params_file(path) == {'sad.window': 7, 'median': True}  # the named entry wins
    path = write(tmp_path, {'renamed_node': {'ros__parameters': {'sad': {'window': 3}}}})
    assert load_params_file(path) == {'sad.window': 3}  # one entry: a dump of a renamed node
    path = write(tmp_path, {'a': {'ros__parameters': {}}, 'b': {'ros__parameters': {}}})
    with pytest.raises(ValueError, match=r'no parameters for gcp_stereo_node.*entries: a, b'):
        load_params_file(path)


@pytest.mark.parametrize('doc, reason', [
    ({'/**': {'ros__parameters': {'P2': 3.0}}},
     r"unknown parameter\(s\) \['P2'\] \(P2: each cost has its own, e\.g\. census\.P2"),
    ({'/**': {'ros__parameters': {'census': {'P1': 'four'}}}},
     "census.P1 takes a float value, got 'four'"),
    ({'/**': {'ros__parameters': {'paths': 12}}}, 'paths must be one of 4, 8, 16, got 12'),
    ({'/**': {'ros__parameters': {'window': 9}}}, r'window: each cost has its own'),
    ({'/**': {'ros__parameters': {'use_gcp': 1}}}, 'use_gcp takes a bool value, got 1'),
    ('/**: [unclosed', 'cannot read parameters file'),
])
def test_bad_files_are_refused_with_the_reason(tmp_path, doc, reason):
    path = write(tmp_path, doc)
    with pytest.raises(ValueError, match=reason):
        config_from_params(load_params_file(path))


def test_both_costs_are_checked_whichever_is_chosen():
    with pytest.raises(ValueError, match=r'sad: P2 \(0\.01\) must be >= P1 \(0\.02\)'):
        config_from_params({'cost': 'census', 'sad.P2': 0.01})
    config = config_from_params({'cost': 'census', 'sad.P2': 20.0, 'census.P2': 30.0})
    assert config.p2 == 30.0


@pytest.mark.parametrize('values, reason', [
    ({'precision': False}, '^precision takes a str value, got False$'),
    ({'precision': 'fp16'}, "^precision must be one of 'auto', 'int8', 'bf16', 'fp32', "
                            "got 'fp16'$"),
    ({'max_disparity': 0}, r'^max_disparity must be in \[1, 1024\], got 0$'),  # its ROS name
])
def test_values_of_neither_cost_are_not_said_of_one(values, reason):
    with pytest.raises(ValueError, match=reason):
        config_from_params(values)


def test_bf16_of_earlier_releases_says_what_it_became():
    """A params file with the old bf16 parameter is refused, naming precision's values."""
    with pytest.raises(ValueError, match=r"bf16 is now precision \('bf16' for bf16 true, "
                                         r"'fp32' for false"):
        config_from_params({'bf16': False})
    for value in ('auto', 'int8', 'bf16', 'fp32'):
        assert config_from_params({'precision': value}).precision == value
