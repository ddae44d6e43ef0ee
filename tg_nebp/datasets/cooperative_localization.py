import os
import pickle
import re
import sys
import warnings
from typing import Callable, List, Optional, Tuple, Union

import torch
import torch.distributed as dist
from torch_geometric.data import InMemoryDataset

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import (check_positive_int, check_realization,
                                     is_integer)
from tg_nebp.datasets.mrclam_dataset import MRCLAM, MRCLAMScenario
from tg_nebp.datasets.uwb import RecordingDataset, RecordingScenario
from tg_nebp.datasets.scenario import Scenario
from tg_nebp.io import atomic_write, first_line, read_json
from tg_nebp.utils import derive_seed, process_group

__all__ = ['CooperativeLocalizationDataset', 'load_datasets',
           'load_scenario']

# bump when the generator or the file layout changes, so old processed files
# are not reused (3: a dictionary of tensors and primitives, no classes)
FORMAT_VERSION = 3
FILE_FORMAT = 'tg_nebp.dataset'


class _UnreadableFile(ValueError):
    r"""A processed file that is cut short or corrupt (not unsafe): it is a
    cache of deterministic data, so it is generated again."""


class CooperativeLocalizationDataset(InMemoryDataset):
    r"""Simulated cooperative-localization sequences of the `"Neural Enhanced
    Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper: mobile agents with
    constant-velocity-with-drag motion, static anchors, and noisy range
    measurements between nodes within the communication range. Each item is
    one :class:`~tg_nebp.data.Realization` (:math:`T` time steps over the
    same nodes); PyG's :class:`~torch_geometric.loader.DataLoader` batches
    them.

    Generation is deterministic in :obj:`seed` (realization :math:`r` uses
    the seed :obj:`derive_seed(seed, r)` :math:`= 1\,000\,003 \cdot`
    :obj:`seed` :math:`+ r`, so a longer dataset extends a
    shorter one). The processed file name holds the scenario name, the number
    of realizations, the seed and a hash of every generation parameter:
    changing any of them generates new data, never reusing stale files.

    The processed file holds tensors and Python primitives only and is read
    with :obj:`torch.load(weights_only=True)`, so loading never runs code
    from it; a file holding anything else is refused with an error naming
    it. A file cut short (a full disk, a copy interrupted) is generated
    again, with a warning. It is written to a temporary name and renamed,
    so a killed run never leaves a half-written file.

    Args:
        root (str, optional): Root directory; data goes to
            :obj:`root/<scenario name>/processed`. (default: :obj:`"datasets"`)
        scenario (str or Scenario, optional): :obj:`"paper_train"`,
            :obj:`"paper_test"`, a path to a scenario JSON file, or a
            :class:`Scenario`. (default: :obj:`"paper_test"`)
        num_realizations (int, optional): Number of sequences; the paper
            uses 100 for training and 400 for testing. (default: :obj:`100`)
        seed (int, optional): Seed of the generation. (default: :obj:`0`)
        transform (callable, optional): Applied on every access.
            (default: :obj:`None`)
        pre_transform (callable, optional): Applied before saving.
            (default: :obj:`None`)
        force_reload (bool, optional): Regenerate even if the processed file
            exists. (default: :obj:`False`)
        log (bool, optional): Print progress while processing.
            (default: :obj:`True`)

    **STATS:**

    .. list-table::
        :header-rows: 1

        * - Name
          - #agents
          - #anchors
          - #steps
          - #edges per step
        * - paper_train
          - 25
          - 5
          - 50
          - ~370
        * - paper_test
          - 100
          - 13
          - 50
          - ~1,200
    """
    def __init__(
        self,
        root: str = 'datasets',
        scenario: Union[str, Scenario] = 'paper_test',
        num_realizations: int = 100,
        seed: int = 0,
        transform: Optional[Callable] = None,
        pre_transform: Optional[Callable] = None,
        force_reload: bool = False,
        log: bool = True,
    ):
        if isinstance(scenario, (str, os.PathLike)):
            scenario = Scenario.load(scenario)
        if not isinstance(scenario, Scenario):
            raise TypeError(f"'scenario' must be a name, a path or a "
                            f"Scenario, got {scenario!r}")
        num_realizations = check_positive_int(num_realizations,
                                              'num_realizations')
        if not is_integer(seed):
            raise TypeError(f"'seed' must be an integer, got {seed!r}")
        if seed < 0:
            raise ValueError(f"'seed' must be non-negative, got {seed}")
        if os.path.exists(root) and not os.path.isdir(root):
            raise ValueError(f"'root' = '{root}' is not a folder")
        self.scenario = scenario
        self.num_realizations = int(num_realizations)
        self.seed = int(seed)
        super().__init__(os.path.join(root, scenario.name), transform,
                         pre_transform, log=log, force_reload=force_reload)
        path = self.processed_paths[0]
        try:
            self.load(path)
        except _UnreadableFile as e:
            warnings.warn(f"{e}; generating it again", stacklevel=2)
            self.process()
            self.load(path)

    @property
    def raw_file_names(self) -> List[str]:
        return []  # simulated: nothing to download

    @property
    def processed_file_names(self) -> List[str]:
        s = self.scenario
        return [f'{s.name}_r{self.num_realizations}_t{s.num_steps}_'
                f'seed{self.seed}_{s.fingerprint()}_v{FORMAT_VERSION}.pt']

    def _process(self):
        # replaces PyG's, which reads processed/pre_transform.pt with
        # weights_only=False (code from a file would run) and writes it in
        # place (a killed run leaves it empty); the pre_transform is recorded
        # in the processed file instead
        if self.force_reload or not os.path.exists(self.processed_paths[0]):
            if self.log and 'PYTEST_CURRENT_TEST' not in os.environ:
                print(f'Generating {self.processed_paths[0]}',
                      file=sys.stderr)
            self.process()

    def load(self, path: str, data_cls=Realization) -> None:
        r"""Reads a processed file with :obj:`weights_only=True`; an unsafe
        or foreign file is refused with a :class:`ValueError` naming it."""
        try:
            state = torch.load(path, map_location='cpu', weights_only=True)
        except pickle.UnpicklingError as e:
            # torch's allow-list refused a class or function: an unsafe file
            # (random bytes fail on an opcode instead, and are regenerated)
            if 'global' in str(e).lower():
                raise ValueError(f"processed file '{path}' holds objects "
                                 f"other than tensors and primitives: "
                                 f"refused (delete it to generate it "
                                 f"again)") from None
            raise _UnreadableFile(f"processed file '{path}' is corrupt: "
                                  f"{first_line(e)}") from None
        except (FileNotFoundError, PermissionError, IsADirectoryError):
            raise
        except Exception as e:  # damaged bytes raise many kinds
            raise _UnreadableFile(f"processed file '{path}' is cut short "
                                  f"or corrupt: {first_line(e)}") from None
        if not (isinstance(state, dict)
                and state.get('format') == FILE_FORMAT
                and state.get('version') == FORMAT_VERSION
                and isinstance(state.get('data'), dict)
                # None for a single realization (PyG's collate)
                and isinstance(state.get('slices', {}), (dict, type(None)))):
            raise ValueError(f"processed file '{path}' is not a tg_nebp "
                             f"dataset of format version {FORMAT_VERSION} "
                             f"(delete it to generate it again)")
        if state.get('pre_transform') != _describe(self.pre_transform):
            warnings.warn(f"'{path}' was generated with the pre_transform "
                          f"{state.get('pre_transform')}, not "
                          f"{_describe(self.pre_transform)}; pass "
                          f"force_reload=True to generate it again",
                          stacklevel=3)
        try:
            self.data = data_cls.from_dict(state['data'])
            self.slices = state['slices']
        except Exception as e:
            raise ValueError(f"processed file '{path}' does not hold "
                             f"realizations: {first_line(e)}") from None

    def process(self):
        data_list = []
        for r in range(self.num_realizations):
            generator = torch.Generator().manual_seed(derive_seed(self.seed,
                                                                  r))
            data = self.scenario.generate(generator)
            check_realization(data)
            if self.pre_transform is not None:
                data = self.pre_transform(data)
            data_list.append(data)
        data, slices = self.collate(data_list)
        state = dict(format=FILE_FORMAT, version=FORMAT_VERSION,
                     data=data.to_dict(), slices=slices,
                     pre_transform=_describe(self.pre_transform))
        # write then rename: a killed run never leaves a half-written file,
        # a failed one no temporary file
        atomic_write(self.processed_paths[0],
                     lambda tmp: torch.save(state, tmp))

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({len(self)}, scenario='
                f'{self.scenario.name}, seed={self.seed})')


def _describe(transform: Optional[Callable]) -> str:
    # repr without memory addresses, which change from run to run
    return re.sub(r' at 0x[0-9a-fA-F]+', '', repr(transform))


def load_scenario(name_or_path: Union[str, os.PathLike]
                  ) -> Union[Scenario, MRCLAMScenario]:
    r"""A simulated :class:`~tg_nebp.datasets.Scenario` or a real
    sequence's :class:`~tg_nebp.datasets.MRCLAMScenario`, by name
    (:obj:`"paper_test"`, :obj:`"mrclam-6"`, ...) or from a JSON file (a
    real sequence's file has a :obj:`"sequence"` field)."""
    text = str(name_or_path)
    if text.startswith('mrclam-') and not text.endswith('.json'):
        return MRCLAMScenario.load(text)
    if text.startswith(('tiers-uwb-', 'miluv-')) and \
            not text.endswith('.json'):
        return RecordingScenario.load(text)
    if text.endswith('.json') and os.path.isfile(text):
        # read once: a real sequence's file has a 'sequence' field, a
        # recording's a 'recording' field
        fields = read_json(text)
        kind = Scenario
        if isinstance(fields, dict) and 'sequence' in fields:
            kind = MRCLAMScenario
        elif isinstance(fields, dict) and 'recording' in fields:
            kind = RecordingScenario
        return kind.from_fields(fields, text)
    return Scenario.load(name_or_path)


def load_datasets(root: str, *specs: Tuple[Union[str, Scenario], Optional[
        int], int]) -> List[Union[CooperativeLocalizationDataset, MRCLAM]]:
    r"""The datasets :obj:`(scenario, num_realizations, seed)`, generated
    once: under an initialized :mod:`torch.distributed` process group rank
    0 generates (or finds) the files first and the other ranks then read
    them, so concurrent processes never write the same file. A real
    sequence's scenario (:class:`~tg_nebp.datasets.MRCLAMScenario`) is
    its :class:`~tg_nebp.datasets.MRCLAM` dataset read from :obj:`root`
    (its first :obj:`num_realizations` windows, all of them for
    :obj:`None`; the seed is not used). Used by :obj:`tg-nebp train`,
    :obj:`evaluate`, :obj:`compare` and :obj:`reproduce`."""
    world_size, rank = process_group()

    def one(scenario, count, seed):
        if isinstance(scenario, (str, os.PathLike)):
            scenario = load_scenario(scenario)
        if isinstance(scenario, MRCLAMScenario):
            return MRCLAM(root, scenario, count, log=False)
        if isinstance(scenario, RecordingScenario):
            return RecordingDataset(root, scenario, count, log=False)
        return CooperativeLocalizationDataset(root, scenario, count, seed,
                                              log=False)

    def load():
        return [one(*spec) for spec in specs]

    if world_size == 1:
        return load()
    # rank 0 tells the others whether it could: a bad scenario is then one
    # error line on every rank, not a broken connection on the others
    outcome = [None]
    if rank == 0:
        try:
            datasets = load()
        except (ValueError, OSError) as e:
            outcome[0] = str(e)
        dist.broadcast_object_list(outcome, src=0)
        if outcome[0] is not None:
            raise ValueError(outcome[0])
        return datasets
    dist.broadcast_object_list(outcome, src=0)
    if outcome[0] is not None:
        raise ValueError(f'rank 0 could not make the data: {outcome[0]}')
    return load()
