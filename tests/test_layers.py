r"""The import graph of the package: the experiment drivers sit above the
library, and nothing below them imports them or the command line."""
import ast
from pathlib import Path

import tg_nebp

PACKAGE = Path(tg_nebp.__file__).parent
# the drivers and the command line; the aliases of the moved modules
ABOVE = ('tg_nebp.experiments', 'tg_nebp.cli', 'tg_nebp.__main__')
ALIASES = {'frontier.py', 'reproduce.py', 'beyond.py', 'bench.py',
           '_moved.py'}


def imported(path: Path):
    r"""Every module that :obj:`path` imports, at any depth of its code."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
            yield from (f'{node.module}.{alias.name}' for alias in node.names)


def test_the_library_imports_no_driver_and_no_cli():
    below = [p for p in PACKAGE.rglob('*.py')
             if not any(part in ('experiments', ) for part in p.parts)
             and p.name not in ALIASES | {'cli.py', '__main__.py'}]
    assert len(below) > 30
    offenders = {str(p.relative_to(PACKAGE)): name for p in below
                 for name in imported(p)
                 if any(name == a or name.startswith(a + '.')
                        for a in ABOVE)}
    assert offenders == {}


def test_the_drivers_live_in_one_subpackage():
    drivers = {p.stem for p in (PACKAGE / 'experiments').glob('*.py')}
    assert {'compare', 'frontier', 'reproduce', 'equivariant_nebp', 'bench',
            'evaluate', 'train'} <= drivers
    # the top level holds the library and the aliases only
    top = {p.name for p in PACKAGE.glob('*.py')}
    assert top & ALIASES == ALIASES
    for alias in ALIASES - {'_moved.py'}:
        assert len((PACKAGE / alias).read_text().splitlines()) < 8


def modules_under(folder: str):
    return list((PACKAGE / folder).rglob('*.py'))


def test_the_bound_and_the_trackers_do_not_lean_on_each_other():
    # the bound is the yardstick of the trackers: what both need (the
    # dense joint's algebra and layout, the checks) sits a floor lower
    for folder, other in (('bounds', 'tg_nebp.filters'),
                          ('filters', 'tg_nebp.bounds')):
        offenders = {str(p.relative_to(PACKAGE)): name
                     for p in modules_under(folder) for name in imported(p)
                     if name == other or name.startswith(other + '.')}
        assert offenders == {}, folder
