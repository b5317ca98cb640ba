"""Commit subjects: imperative summaries of at most 72 characters (CONTRIBUTING.md)."""
from pathlib import Path
import shutil
import subprocess

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The first commit under the rule; the history before it is left as it was written.
RULE_FROM = 'Group the CUDA twins in stereo/cuda/ and the CNN in stereo/cnn/'
LIMIT = 72


def subjects():
    """Return the subjects of HEAD's history, newest first ([] without git or its history)."""
    if shutil.which('git') is None or not (ROOT / '.git').exists():
        return []
    proc = subprocess.run(['git', 'log', '--format=%s'], cwd=ROOT, capture_output=True,
                          text=True)
    return proc.stdout.splitlines() if proc.returncode == 0 else []


def test_commit_subjects_since_the_rule_fit_in_72_characters():
    found = subjects()
    if RULE_FROM not in found:
        pytest.skip('this checkout has no history back to the rule (a shallow clone)')
    since = found[:found.index(RULE_FROM) + 1]
    long = [s for s in since if len(s) > LIMIT]
    assert not long, long
    # an imperative verb first ("Add", "Split"), not a file or a name and a colon
    labelled = [s for s in since if not s[:1].isupper() or s.split(' ')[0].endswith(':')]
    assert not labelled, labelled
