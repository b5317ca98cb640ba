"""gcp-stereo-train --init: training starts from given weights and records them."""
from gcp_stereo_ros.stereo.cnn.network import load_net
from gcp_stereo_ros.stereo.cnn.weights import DEFAULT_WEIGHTS
from gcp_stereo_ros.tools import train
import torch


def test_init_starts_from_the_given_weights_and_records_them(data_dir, tmp_path):
    """One step at a learning rate of 1e-9 leaves the shipped weights as they were."""
    threads = torch.get_num_threads()
    try:
        train.main(['--dataset', str(data_dir / 'middlebury_v2'), '--frames', 'tsukuba',
                    '--epochs', '1', '--samples-per-epoch', '4', '--batch-size', '4',
                    '--threads', '1', '--lr', '1e-9', '--init', str(DEFAULT_WEIGHTS),
                    '--out', str(tmp_path / 'ft.pt')])
    finally:
        torch.set_num_threads(threads)
    shipped, tuned = load_net(), load_net(tmp_path / 'ft.pt')
    for key, weight in shipped.state_dict().items():
        torch.testing.assert_close(tuned.state_dict()[key], weight, rtol=0, atol=1e-6)
    init = tuned.meta['init']
    assert init['weights'] == str(DEFAULT_WEIGHTS)
    assert init['command'] == shipped.meta['command']
    assert init['seconds'] == shipped.meta['seconds'] > 1000
    assert tuned.meta['command'].endswith(f'--init {DEFAULT_WEIGHTS} --out {tmp_path / "ft.pt"}')
