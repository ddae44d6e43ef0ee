r"""The import graph of the package: the experiment drivers sit above the
library, and nothing below them imports them or the command line; no
circle of imports (those inside functions and under TYPE_CHECKING
included: they hide a circle at run time without cutting it; a package's
imports of its own modules, re-exports, are edges too)."""
import ast
from pathlib import Path

import tg_nebp

PACKAGE = Path(tg_nebp.__file__).parent
# the drivers and the command line
ABOVE = ('tg_nebp.experiments', 'tg_nebp.cli', 'tg_nebp.cli_commands',
         'tg_nebp.__main__')


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
             and p.name not in {'cli.py', 'cli_commands.py', '__main__.py'}]
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
    # the top level holds the library only: the one-release aliases of
    # the moved drivers are gone
    top = {p.name for p in PACKAGE.glob('*.py')}
    assert not top & {'frontier.py', 'reproduce.py', 'beyond.py',
                      'bench.py', '_moved.py'}


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


def _modules():
    # every module of the package by dotted name
    out = {}
    for path in PACKAGE.rglob('*.py'):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix('').parts)
        if parts[-1] == '__init__':
            parts = parts[:-1]
        out['.'.join(parts)] = path
    return out


def import_graph():
    r"""Every module of the package and the package modules it imports."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        package = name if path.name == '__init__.py' else \
            name.rpartition('.')[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ''
                if node.level:
                    parts = package.split('.')
                    parts = parts[:len(parts) - node.level + 1]
                    base = '.'.join(parts + ([base] if base else []))
                for alias in node.names:
                    # a submodule by name, else a name of the module
                    target = f'{base}.{alias.name}'
                    target = target if target in modules else base
                    if target in modules:
                        edges.add(target)
        graph[name] = edges - {name}
    return graph


def cycles(graph):
    r"""The strongly connected components of more than one module."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []

    def visit(start):
        # Tarjan's algorithm, iterative (no recursion limit)
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_package_has_no_circle_of_imports():
    graph = import_graph()
    assert 'tg_nebp.models.base' in graph and len(graph) > 50
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_circle():
    # a circle through a function's import, and one through a package's
    # re-export, are found; a chain is not a circle
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [
        ['a', 'b', 'c']]
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': set()}) == []
    graph = import_graph()
    graph['tg_nebp.data.validation'].add('tg_nebp.models')
    assert any('tg_nebp.data.validation' in c for c in cycles(graph))


def test_the_trackers_live_in_their_families_and_import_as_before():
    # particle, Gaussian (with their windows), centralized and live: each a
    # subpackage; every public name imports from tg_nebp.filters, and a
    # module's path before the families imports as the same module
    import importlib
    import tg_nebp.filters as filters
    families = ('particle', 'gaussian', 'centralized', 'live')
    listed = set()
    for family in families:
        package = importlib.import_module(f'tg_nebp.filters.{family}')
        assert set(package.__all__) <= set(filters.__all__), family
        for name in package.__all__:
            assert getattr(filters, name) is getattr(package, name)
        listed |= set(package.__all__)
    # what the top keeps besides: the shared time loop and its state
    assert set(filters.__all__) - listed == {
        'Tracker', 'StepOutput', 'TrackOutput', 'Smoothed', 'StateField',
        'FIELD_KINDS', 'check_state', 'check_state_dim', 'weighted_moments'}
    assert {p.name for p in (PACKAGE / 'filters').glob('*.py')} == {
        '__init__.py', 'tracker.py', 'state.py'}
    for family, names in filters._FAMILIES.items():
        for name in names:
            moved = importlib.import_module(f'tg_nebp.filters.{family}.{name}')
            assert importlib.import_module(f'tg_nebp.filters.{name}') is moved
    from tg_nebp.filters.gaussian_bp import GaussianBP
    assert GaussianBP is filters.GaussianBP
