import os
from typing import Callable, List, Optional, Union

import torch
from torch_geometric.data import InMemoryDataset

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_realization
from tg_nebp.datasets.scenario import Scenario
from tg_nebp.io import atomic_write

__all__ = ['CooperativeLocalizationDataset']

# bump when the generator changes, so old processed files are not reused
FORMAT_VERSION = 2


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
    the seed :obj:`seed * 1_000_003 + r`, so a longer dataset extends a
    shorter one). The processed file name holds the scenario name, the number
    of realizations, the seed and a hash of every generation parameter:
    changing any of them generates new data, never reusing stale files.

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
        if not isinstance(scenario, Scenario):
            scenario = Scenario.load(scenario)
        if int(num_realizations) < 1:
            raise ValueError(f"'num_realizations' must be at least 1, got "
                             f"{num_realizations}")
        if int(seed) < 0:
            raise ValueError(f"'seed' must be non-negative, got {seed}")
        self.scenario = scenario
        self.num_realizations = int(num_realizations)
        self.seed = int(seed)
        super().__init__(os.path.join(root, scenario.name), transform,
                         pre_transform, log=log, force_reload=force_reload)
        self.load(self.processed_paths[0], data_cls=Realization)

    @property
    def raw_file_names(self) -> List[str]:
        return []  # simulated: nothing to download

    @property
    def processed_file_names(self) -> List[str]:
        s = self.scenario
        return [f'{s.name}_r{self.num_realizations}_t{s.num_steps}_'
                f'seed{self.seed}_{s.fingerprint()}_v{FORMAT_VERSION}.pt']

    def download(self):
        pass

    def process(self):
        data_list = []
        for r in range(self.num_realizations):
            generator = torch.Generator().manual_seed(self.seed * 1_000_003 +
                                                      r)
            data = self.scenario.generate(generator)
            check_realization(data)
            if self.pre_transform is not None:
                data = self.pre_transform(data)
            data_list.append(data)
        # write then rename: a killed run never leaves a half-written file,
        # a failed one no temporary file
        atomic_write(self.processed_paths[0],
                     lambda tmp: self.save(data_list, tmp))

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({len(self)}, scenario='
                f'{self.scenario.name}, seed={self.seed})')
