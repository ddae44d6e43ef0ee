from .scenario import Scenario
from .cooperative_localization import (CooperativeLocalizationDataset,
                                       load_datasets)
from .mrclam import (MRCLAMSequence, fit_models, integrate_odometry,
                     interpolate_pose, mrclam_realization, read_mrclam)

__all__ = ['Scenario', 'CooperativeLocalizationDataset', 'load_datasets',
           'MRCLAMSequence', 'read_mrclam', 'mrclam_realization',
           'integrate_odometry', 'interpolate_pose', 'fit_models']
