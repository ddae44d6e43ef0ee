from .scenario import Scenario
from .mrclam import (MRCLAMSequence, fit_models, integrate_odometry,
                     interpolate_pose, mrclam_realization, read_mrclam)
from .mrclam_dataset import (MRCLAM, MRCLAMScenario, fitted_scenario,
                             range_part)
from .cooperative_localization import (CooperativeLocalizationDataset,
                                       load_datasets, load_scenario)

__all__ = ['Scenario', 'CooperativeLocalizationDataset', 'load_datasets',
           'load_scenario', 'MRCLAM', 'MRCLAMScenario', 'fitted_scenario',
           'range_part', 'MRCLAMSequence', 'read_mrclam',
           'mrclam_realization', 'integrate_odometry', 'interpolate_pose',
           'fit_models']
