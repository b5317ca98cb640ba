"""gcp-stereo-plot training: the curves of the shipped weights' own training run."""
from gcp_stereo_ros.stereo.cnn import DEFAULT_WEIGHTS
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
