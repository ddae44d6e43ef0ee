r"""The README is a landing page: short, its tables well formed, and every
local link and image present."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]


def tables(text: str):
    r"""Every Markdown table of :obj:`text` as its list of rows, code
    blocks left out."""
    text = re.sub(r'```.*?```', '', text, flags=re.S)
    rows = []
    for line in text.splitlines() + ['']:
        if line.lstrip().startswith('|'):
            rows.append(line.strip())
        elif rows:
            yield rows
            rows = []


def cells(row: str) -> int:
    # a \| inside a cell is text, not a border
    return len(re.split(r'(?<!\\)\|', row.strip().strip('|')))


def test_readme_is_short():
    assert len((ROOT / 'README.md').read_text().splitlines()) <= 250


@pytest.mark.parametrize('page', PAGES, ids=lambda p: p.name)
def test_tables_are_well_formed(page):
    for rows in tables(page.read_text()):
        header, rule = rows[0], rows[1] if len(rows) > 1 else ''
        assert re.fullmatch(r'\|( *:?-+:? *\|)+', rule), \
            f'{page.name}: a table without a header: {header}'
        width = cells(header)
        for row in rows[2:]:
            assert cells(row) == width, f'{page.name}: {row}'


@pytest.mark.parametrize('page', PAGES, ids=lambda p: p.name)
def test_local_links_and_images_exist(page):
    text = re.sub(r'```.*?```', '', page.read_text(), flags=re.S)
    targets = re.findall(r'\]\(([^)\s]+)\)', text)
    local = [t.split('#')[0] for t in targets
             if not re.match(r'[a-z]+://|mailto:|#', t)]
    assert page.name != 'README.md' or len(local) > 10
    missing = [t for t in local if not (page.parent / t).exists()]
    assert missing == []
