from .scenario import Scenario
from .cooperative_localization import (CooperativeLocalizationDataset,
                                       load_datasets)

__all__ = ['Scenario', 'CooperativeLocalizationDataset', 'load_datasets']
