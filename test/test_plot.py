"""gcp-stereo-plot: the curves of the shipped weights' own training run, and a sweep."""
import json

from gcp_stereo_ros.stereo.cnn.weights import DEFAULT_WEIGHTS
from gcp_stereo_ros.tools import plot
import matplotlib.image
import numpy as np
import torch


def test_training_curves_of_the_shipped_weights(tmp_path, capsys):
    history = torch.load(DEFAULT_WEIGHTS, weights_only=True)['meta']['history']
    plot.main(['training', '--weights', str(DEFAULT_WEIGHTS), '--out', str(tmp_path)])
    out = capsys.readouterr().out
    last = history[-1]['val']
    loss = np.mean([v['loss'] for v in last.values()])
    wta = np.mean([v['wta_accuracy'] for v in last.values()])
    assert (f'{len(history)} epochs, {history[-1]["seconds"] / 3600:.2f} h: final validation '
            f'loss {loss:.4f}, WTA accuracy {wta:.2f} %') in out
    image = matplotlib.image.imread(tmp_path / 'training.png')
    assert image.shape[1] > 2 * image.shape[0] > 600  # three panels side by side
    assert image[..., :3].std() > 0.05  # drawn, not blank


def test_training_curves_need_a_training_file(tmp_path, capsys):
    bad = tmp_path / 'bad.pt'
    torch.save({'state_dict': {}}, bad)
    assert plot.main(['training', '--weights', str(bad), '--out', str(tmp_path)]) == 1
    assert f'{bad}: not gcp-stereo-train weights or a checkpoint' in capsys.readouterr().err
    assert not (tmp_path / 'training.png').exists()


def test_a_sweep_takes_switches(tmp_path, data_dir):
    """--grid takes true/false: here gcp_plain_check, which leaves fewer, surer GCPs."""
    assert plot.main(['sweep', '--dataset', str(data_dir), '--frames', 'middlebury_v2/tsukuba',
                      '--method', 'census+gcp', '--grid', 'gcp_plain_check=true,false',
                      '--set', 'precision=fp32', '--out', str(tmp_path)]) == 0
    rows = json.loads((tmp_path / 'sweep_census_gcp.json').read_text())
    on, off = sorted(rows, key=lambda r: not r['gcp_plain_check'])
    # measured: 90.9 / 99.33 % and 92.7 / 98.75 % (density / accuracy), bad3 2.68 and 2.90 %
    assert on['gcp_plain_check'] is True and off['gcp_plain_check'] is False
    assert off['gcp_density'] - 3 < on['gcp_density'] < off['gcp_density'] - 1
    assert on['gcp_accuracy'] > off['gcp_accuracy'] + 0.3 and on['bad3'] < off['bad3']
    image = matplotlib.image.imread(tmp_path / 'sweep_census_gcp.png')
    assert image[..., :3].std() > 0.05  # drawn, not blank
