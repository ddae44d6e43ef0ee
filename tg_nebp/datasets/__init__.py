from .scenario import Scenario
from .cooperative_localization import CooperativeLocalizationDataset

__all__ = ['Scenario', 'CooperativeLocalizationDataset']
