"""
The manual: `make docs`'s Sphinx build passes without a warning, and what it generates is right.

The parameter table is checked against the node's declarations (every parameter, its type,
default, range or choices and description), the API page against the classes it documents,
and the README's links into the manual against the built pages.
"""
import html
from html.parser import HTMLParser
import inspect
from pathlib import Path
import re
import subprocess
import sys

from gcp_stereo_ros.ros.params import coerce, PARAMS
import pytest

ROOT = Path(__file__).resolve().parents[1]
ROS_TYPES = {bool: 'boolean', int: 'integer', float: 'double', str: 'string'}


@pytest.fixture(scope='module')
def built(tmp_path_factory):
    """Build the manual as `make docs` does (fresh, warnings are errors) into a temporary dir."""
    out = tmp_path_factory.mktemp('docs')
    proc = subprocess.run(
        [sys.executable, '-m', 'sphinx', '-W', '--keep-going', '-E', '-q', '-b', 'html',
         str(ROOT / 'doc'), str(out)], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out, proc


class _Tables(HTMLParser):
    """Collect the text of every table cell, row by row, of the tables with a class."""

    def __init__(self, css_class):
        super().__init__()
        self.css_class, self.rows, self._in, self._row, self._cell = css_class, [], 0, None, None

    def handle_starttag(self, tag, attrs):
        if tag == 'table' and self.css_class in (dict(attrs).get('class') or '').split():
            self._in += 1
        elif self._in and tag == 'tr':
            self._row = []
        elif self._in and tag in ('td', 'th'):
            self._cell = []

    def handle_endtag(self, tag):
        if tag == 'table' and self._in:
            self._in -= 1
        elif self._in and tag in ('td', 'th') and self._cell is not None:
            self._row.append(' '.join(''.join(self._cell).split()))
            self._cell = None
        elif self._in and tag == 'tr' and self._row is not None:
            self.rows.append(self._row)
            self._row = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def _documented(cls):
    """Yield (name, docstring) of what autodoc's `:members:` shows of `cls`: documented methods."""
    for name, member in vars(cls).items():
        doc = inspect.getdoc(member)
        if doc and (not name.startswith('_') or name == '__call__') and (
                callable(member) or isinstance(member, (classmethod, property))):
            yield name, doc


def test_the_manual_builds_without_a_warning(built):
    out, proc = built
    assert 'WARNING' not in proc.stderr and 'ERROR' not in proc.stderr, proc.stderr
    pages = {p.stem for p in (ROOT / 'doc').glob('*.md')}
    assert len(pages) >= 12 and all((out / f'{page}.html').is_file() for page in pages)
    assert (out / 'index.html').is_file()


def test_every_parameter_is_in_the_table_as_declared(built):
    out, _ = built
    parser = _Tables('gcp-parameters')
    parser.feed((out / 'parameters.html').read_text())
    header, *rows = parser.rows
    assert header == ['parameter', 'type', 'default', 'range', 'description']
    table = {row[0]: row[1:] for row in rows}
    assert list(table) == [p.name for p in PARAMS]  # every one, in the declared order
    for p in PARAMS:
        kind, default, limits, description = table[p.name]
        value = coerce(p.name, p.default)  # what the node declares
        assert kind == ROS_TYPES[type(value)], p.name
        assert default == (str(value).lower() if isinstance(value, bool) else repr(value)), p.name
        assert description == ' '.join(p.description.split()), p.name
        if p.range is not None:
            low, high, step = p.range
            assert limits.startswith(f'{low!r} .. {high!r}'), (p.name, limits)
            assert (f'step {step!r}' in limits) == bool(step), (p.name, limits)
        if p.choices:
            assert limits.endswith('one of ' + ', '.join(map(str, p.choices))), (p.name, limits)
        if p.range is None and not p.choices:
            assert limits == '', (p.name, limits)


def test_the_api_page_documents_the_classes_from_their_docstrings(built):
    out, _ = built
    page = (out / 'api.html').read_text()
    text = ' '.join(html.unescape(page).split())
    from gcp_stereo_ros.stereo.config import StereoConfig
    from gcp_stereo_ros.stereo.pipeline import StereoPipeline, StereoResult
    for cls in (StereoConfig, StereoPipeline, StereoResult):
        assert f'id="{cls.__module__}.{cls.__name__}"' in page, cls
    documented = {(cls, name): doc for cls in (StereoConfig, StereoPipeline, StereoResult)
                  for name, doc in _documented(cls)}
    assert {'for_cost', '__call__', 'release'} <= {name for _, name in documented}
    for (cls, name), doc in documented.items():  # each, with its docstring's first line
        assert f'id="{cls.__module__}.{cls.__name__}.{name}"' in page, name
        first = doc.splitlines()[0].split('`')[0]
        assert ' '.join(first.split()) in text, name


def test_the_readme_links_into_the_manual_resolve(built):
    out, _ = built
    readme = (ROOT / 'README.md').read_text()
    links = re.findall(r'\]\(doc/([\w/]+)\.md(?:#([\w-]+))?\)', readme)
    assert len({page for page, _ in links}) >= 12, links
    for page, anchor in links:
        assert (ROOT / 'doc' / f'{page}.md').is_file(), page
        if anchor:
            assert f'id="{anchor}"' in (out / f'{page}.html').read_text(), (page, anchor)
    lines = readme.splitlines()
    assert len(lines) <= 120, len(lines)  # a front page; the rest is the manual's
    # the only two set-up commands, both on the first screen
    assert [line.split()[:2] for line in lines if line.startswith('make ')] == [
        ['make', 'demo'], ['make', 'test']]
    assert lines.index(next(line for line in lines if line.startswith('make test'))) < 30
