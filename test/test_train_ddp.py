"""Training with torchrun: two CPU processes (gloo, DDP) take the steps one process takes."""
import os
from pathlib import Path
import subprocess
import sys

from gcp_stereo_ros.tools import train
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def test_ddp_two_processes_follow_one_process_and_resume(data_dir, tmp_path):
    """
    Resume a one-process checkpoint in 2 torchrun processes: the same losses and weights.

    Epoch 1 of 2 steps runs in this process; epochs 2 and 3 (4 steps of 4 crops, 2 per
    process) in two; rank 0 alone reports and writes checkpoints and weights.
    """
    common = ['--dataset', str(data_dir / 'middlebury_v2'), '--frames', 'tsukuba',
              '--epochs', '3', '--samples-per-epoch', '8', '--batch-size', '4', '--threads', '1']
    threads = torch.get_num_threads()
    try:
        train.main([*common, '--checkpoint-dir', str(tmp_path / 'one'),
                    '--out', str(tmp_path / 'one.pt')])
    finally:
        torch.set_num_threads(threads)
    proc = subprocess.run(
        [sys.executable, '-m', 'torch.distributed.run', '--standalone', '--nproc-per-node', '2',
         '-m', 'gcp_stereo_ros.tools.train', *common, '--resume',
         str(tmp_path / 'one' / 'epoch_001.pt'), '--checkpoint-dir', str(tmp_path / 'two'),
         '--out', str(tmp_path / 'two.pt')],
        cwd=REPO, env=os.environ, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count('epoch 3: train loss') == 1, proc.stdout
    assert sorted(p.name for p in (tmp_path / 'two').iterdir()) == ['epoch_002.pt',
                                                                    'epoch_003.pt']
    one, two = (torch.load(tmp_path / f'{n}.pt', weights_only=True) for n in ('one', 'two'))
    assert two['meta']['processes'] == 2
    losses = [[h['train_loss'] for h in blob['meta']['history']] for blob in (one, two)]
    assert len(losses[1]) == 3 and losses[0][0] == losses[1][0]  # epoch 1 from the checkpoint
    np.testing.assert_allclose(losses[1], losses[0], rtol=0, atol=1e-4)
    assert losses[0][1] != losses[0][2]  # the steps did change the net
    for key, weight in one['state_dict'].items():
        np.testing.assert_allclose(two['state_dict'][key], weight, rtol=0, atol=1e-4)
    last = torch.load(tmp_path / 'two' / 'epoch_003.pt', weights_only=True)['net']
    for key, weight in last.items():
        assert torch.equal(weight, two['state_dict'][key])
