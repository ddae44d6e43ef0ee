r"""Sphinx configuration of the tg_nebp documentation.

Build (warnings are errors, unresolved cross-references included), from the
repository root: ``.ci/docs``, i.e.
``python3 -m sphinx -E -n -W --keep-going -b html docs docs/_build/html``.
"""
import datetime
import importlib
import inspect
import os
import sys
import time

import jinja2

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), '..'))
# document this checkout's code, not whatever tg_nebp is installed
sys.path.insert(0, ROOT)

import tg_nebp  # noqa: E402

project = 'tg_nebp'
author = 'tg_nebp contributors'
copyright = f'{datetime.date.today().year}, {author}'
version = release = tg_nebp.__version__

extensions = [
    'sphinx.ext.autodoc',
    'sphinx.ext.autosummary',
    'sphinx.ext.napoleon',
    'sphinx.ext.mathjax',
    'sphinx.ext.viewcode',
    'sphinxarg.ext',
    'myst_nb',
]

source_suffix = {'.rst': 'restructuredtext', '.md': 'myst-nb',
                 '.ipynb': 'myst-nb'}
root_doc = 'index'
# the figures and tables that README.md links to live in docs/ as well;
# the tables are included by results.md, not pages of their own
exclude_patterns = ['_build', 'frontier_*.md', 'compare_*.md',
                    'cli_outputs.md', '**/.ipynb_checkpoints']

# -- cross-references -------------------------------------------------------

# Every :class:, :func:, :meth:, :attr: and :mod: reference must resolve
# (-n). These names are exempt, nothing else:
# - :obj: follows PyG's docstring convention, in which it marks literals
#   and argument names (:obj:`None`, :obj:`"bp"`, :obj:`num_particles`)
#   as often as objects, so it is not required to resolve;
# - the build has no network, hence no intersphinx: names of Python,
#   PyTorch, PyG, NumPy and Matplotlib cannot be resolved;
# - the words of the Args: blocks' types that are no names ("optional").
nitpicky = True
nitpick_ignore_regex = [
    (r'py:obj', r'(?s).*'),
    (r'py:.*', r'(torch|torch_geometric|torch_sparse|numpy|matplotlib|'
               r'argparse|pathlib|typing|collections|os)(\..*)?'),
    (r'py:class', r'optional|iterable|sequence'),
    (r'py:.*', r'(None|True|False|int|float|bool|str|bytes|dict|list|'
               r'tuple|set|callable|object|type|Tensor|Generator|'
               r'Exception|ValueError|TypeError|OSError|RuntimeError|'
               r'BaseException|NamedTuple|EdgeIndex|Data|Batch|Dataset|'
               r'InMemoryDataset|MessagePassing|Module|Path)'),
]

# -- autodoc, napoleon ------------------------------------------------------

autodoc_member_order = 'bysource'
autodoc_typehints = 'none'  # the Args: blocks give the types, as in PyG
autosummary_generate = False  # tables only; the pages hold the objects

napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_preprocess_types = False
napoleon_custom_sections = ['Shapes']

add_module_names = False
# quotes and ellipses, but no dashes: '--flag' must stay two hyphens in the
# CLI reference
smartquotes_action = 'qe'
python_display_short_literal_types = True

# -- notebooks --------------------------------------------------------------

# docs/examples links to ../examples: the notebooks stay where they are,
# stored without outputs. They are executed here, not by myst-nb (which
# would run them in docs/examples), see execute_notebook() below.
nb_execution_mode = 'off'
nb_merge_streams = True
# the notebooks' only stderr output is tqdm's warning that ipywidgets is
# missing (and its progress bars where one runs): not content
nb_output_stderr = 'remove'
# set TG_NEBP_DOCS_EXECUTE=0 to render the notebooks without running them
EXECUTE_NOTEBOOKS = os.environ.get('TG_NEBP_DOCS_EXECUTE', '1') != '0'
NOTEBOOK_CELL_TIMEOUT = 600  # seconds per cell

myst_enable_extensions = ['dollarmath', 'amsmath']

# -- HTML -------------------------------------------------------------------

html_theme = 'furo'
html_title = f'tg_nebp {release}'


# -- build steps ------------------------------------------------------------

def public(module: str):
    r"""The names of :obj:`module.__all__`, in their order."""
    return [name for name in importlib.import_module(module).__all__
            if not name.startswith('_')]


# the packages and modules that have a page in docs/api
API_PAGES = ['tg_nebp.nn.conv', 'tg_nebp.filters', 'tg_nebp.models',
             'tg_nebp.bounds', 'tg_nebp.gaussian',
             'tg_nebp.experiments.evaluate', 'tg_nebp.experiments.options',
             'tg_nebp.experiments.train',
             'tg_nebp.experiments.compare', 'tg_nebp.experiments.frontier',
             'tg_nebp.experiments.reproduce',
             'tg_nebp.experiments.equivariant_nebp',
             'tg_nebp.experiments.bench', 'tg_nebp.experiments.track',
             'tg_nebp.data', 'tg_nebp.datasets', 'tg_nebp.metrics',
             'tg_nebp.evaluation', 'tg_nebp.live', 'tg_nebp.training',
             'tg_nebp.training_log', 'tg_nebp.plot',
             'tg_nebp.io', 'tg_nebp.utils', 'tg_nebp.threads', 'tg_nebp.ops',
             'tg_nebp.reference']


def defined_in(module: str, name: str) -> str:
    r"""The module that defines :obj:`module.name`: a class's or function's
    own, or for data the deepest module of the package that lists it in
    :obj:`__all__` (where its :obj:`#:` doc comment is)."""
    obj = getattr(importlib.import_module(module), name)
    if inspect.isclass(obj) or inspect.isroutine(obj):
        return obj.__module__
    return max((other for other, mod in list(sys.modules.items())
                if (other == module or other.startswith(module + '.'))
                and name in getattr(mod, '__all__', ())
                and getattr(mod, name, None) is obj), key=len)


def home(module: str, name: str) -> str:
    r"""The full name under which the reference describes
    :obj:`module.name`, on the page of the package that defines it, so that
    every object is described once however often it is re-exported."""
    obj = getattr(importlib.import_module(module), name)
    if inspect.ismodule(obj):
        return obj.__name__
    defined = defined_in(module, name)
    if not (inspect.isclass(obj) or inspect.isroutine(obj)):
        return f'{defined}.{name}'
    page = max((page for page in API_PAGES
                if defined == page or defined.startswith(page + '.')),
               key=len)
    return f'{page}.{name}'


def pyg_class(name: str) -> type:
    r"""The class of the full name :obj:`name`."""
    module, _, cls = name.rpartition('.')
    return getattr(importlib.import_module(module), cls)


def summary_entry(module: str, name: str) -> str:
    r"""The autosummary entry of :obj:`module.name` on the page of
    :obj:`module`: its :func:`home`, relative to :obj:`module` as
    autosummary wants it, shown by its last name."""
    full = home(module, name)
    if full.startswith(module + '.'):
        full = full[len(module) + 1:]
    return f'~{full}'


# PyG's hooks that a subclass overrides for PyG to call (MessagePassing's
# propagate, Dataset's processing): their inherited docstrings describe
# PyG's interface, not the class
PYG_HOOKS = {
    'torch_geometric.nn.conv.MessagePassing': (
        'message', 'aggregate', 'message_and_aggregate', 'update',
        'edge_update'),
    'torch_geometric.data.Dataset': (
        'raw_file_names', 'processed_file_names', 'download', 'process'),
}


def reference(module: str, names=None, header: bool = True) -> str:
    r"""The reST of the reference of :obj:`module`: its docstring, a
    summary table of its public names and the description of each one
    that it defines (re-exported names link to their own page). A page
    in sections (the families of :mod:`tg_nebp.filters`) gives each
    section's :obj:`names` and the module's docstring (:obj:`header`) in
    its first only."""
    mod = importlib.import_module(module)
    names = public(module) if names is None else names
    lines = ([f'.. automodule:: {module}', ''] if header else []) + [
        f'.. currentmodule:: {module}', '',
        '.. autosummary::', '   :nosignatures:', '']
    lines += [f'   {summary_entry(module, name)}' for name in names]
    lines.append('')
    for name in names:
        full = home(module, name)
        if not (full == f'{module}.{name}' or
                defined_in(module, name).startswith(module + '.')):
            continue  # described on another page
        obj = getattr(mod, name)
        if inspect.isclass(obj):
            lines += [f'.. autoclass:: {name}', '   :members:',
                      '   :show-inheritance:']
            hooks = [hook for base, names in PYG_HOOKS.items()
                     if issubclass(obj, pyg_class(base)) for hook in names]
            if hooks:
                lines.append('   :exclude-members: ' + ', '.join(hooks))
        elif callable(obj):
            lines.append(f'.. autofunction:: {name}')
        else:
            lines.append(f'.. autodata:: {full}')
            if len(repr(obj)) > 79:
                lines.append('   :no-value:')
        lines.append('')
    return '\n'.join(lines)


def public_except(module: str, *others: str):
    r"""The public names of :obj:`module` that none of the modules
    :obj:`others` lists (what a package keeps besides its subpackages')."""
    taken = {name for other in others for name in public(other)}
    return [name for name in public(module) if name not in taken]


def render_api_page(app, docname, source):
    r"""The pages of docs/api are Jinja templates: :obj:`reference(module)`
    writes a module's reference from its :obj:`__all__` (as PyG's package
    reference does), so the pages list exactly the public API."""
    if docname.startswith('api/'):
        source[0] = jinja2.Template(source[0]).render(
            reference=reference, public=public,
            public_except=public_except, summary_entry=summary_entry)


def execute_notebook(app, docname, source):
    r"""Runs an example notebook as its test does
    (tests/examples/test_notebooks.py): the repository root as working
    directory, so that the relative path 'datasets' is the repository's
    dataset folder, one OpenMP thread, and a cell error fails the build.
    The outputs exist only in the build, never in the stored notebook."""
    if not docname.startswith('examples/') or not EXECUTE_NOTEBOOKS:
        return
    import nbclient
    import nbformat
    from sphinx.util import logging
    nb = nbformat.reads(source[0], as_version=4)
    env = dict(os.environ, OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join(
                   [ROOT, *filter(None, [os.environ.get('PYTHONPATH')])]))
    start = time.perf_counter()
    nbclient.NotebookClient(
        nb, timeout=NOTEBOOK_CELL_TIMEOUT, kernel_name='python3',
        resources={'metadata': {'path': ROOT}}).execute(env=env)
    logging.getLogger(__name__).info(
        f'executed {docname} in {time.perf_counter() - start:.0f} s')
    source[0] = nbformat.writes(nb)


def setup(app):
    app.connect('source-read', render_api_page)
    app.connect('source-read', execute_notebook)
