"""
Sphinx configuration of the gcp_stereo_ros manual (MyST Markdown pages, autodoc API).

`make docs` builds it into build/docs with warnings as errors; rosdoc2 finds it here
(doc/conf.py, its standard place), runs it inside its own wrapping conf.py and adds its
theme, intersphinx and sphinx-apidoc pages. The API page imports the package: from this
checkout, also under rosdoc2 (else as installed).
"""
from pathlib import Path
import re
import sys


def _doc_dir():
    """
    Return the doc/ folder of the checkout.

    rosdoc2 runs this file from its own conf.py in a copy of doc/, which names this file in an
    `exec(open(...))` line; Sphinx alone runs it in place.
    """
    here = Path(__file__).resolve().parent
    run_by = re.search(r'exec\(open\("([^"]+)"\)', Path(__file__).read_text())
    if run_by and Path(run_by.group(1)).is_file():
        return Path(run_by.group(1)).resolve().parent
    return here


HERE = Path(__file__).resolve().parent  # doc/, or rosdoc2's copy of it
REPO = _doc_dir().parent
sys.path.insert(0, str(HERE / 'ext'))
if (REPO / 'gcp_stereo_ros' / '__init__.py').is_file():  # else the installed package
    sys.path.insert(0, str(REPO))

project = 'gcp_stereo_ros'
author = 'gcp_stereo_ros maintainers'
copyright = 'gcp_stereo_ros maintainers, BSD-3-Clause'  # noqa: A001 (Sphinx's name)
if (REPO / 'package.xml').is_file():  # else rosdoc2 sets them from its package.xml
    release = re.search(r'<version>([^<]+)</version>',
                        (REPO / 'package.xml').read_text()).group(1)
    version = '.'.join(release.split('.')[:2])

extensions = ['myst_parser', 'sphinx.ext.autodoc', 'gcp_parameters']
source_suffix = {'.rst': 'restructuredtext', '.md': 'markdown'}
root_doc = 'index'
exclude_patterns = ['_build', 'ext', 'images/README.md']  # the pictures' provenance
myst_heading_anchors = 3  # `page.md#a-heading` links
autodoc_member_order = 'bysource'
smartquotes = False  # quotes as typed: 'census' as ros2 param describe prints it
html_theme = 'alabaster'
html_static_path = []
