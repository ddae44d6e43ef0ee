from .scenario import RecordedScenarioFields, Scenario, ScenarioModels
from .mrclam import (FIT_HORIZON, MRCLAMSequence, fit_models,
                     integrate_odometry, interpolate_pose, long_run_factor,
                     mrclam_realization, read_mrclam)
from .mrclam_dataset import (MRCLAM, PARTS, MRCLAMScenario, fitted_scenario,
                             range_part, sequence_source, MRCLAM_URL)
from .recording import (BIN_COUNTS, MERGES, READ_COUNTS, Links, Recording,
                        RangeCalibration, merge_links, recording_realization,
                        recording_report, step_of)
from .rosbag import RANGE_TYPES, BagTopics, TIERS_TOPICS, read_bag
from .miluv import read_miluv, miluv_experiments
from .uwb import (RecordingScenario, RecordingDataset, fit_range_models,
                  fitted_recording_scenario, MIN_SIGMA, READERS,
                  RECORDING_PARTS, UWB_FIT_HORIZON, UWB_MIN_NU)
from .cooperative_localization import (CooperativeLocalizationDataset,
                                       load_datasets, load_scenario)

__all__ = ['Scenario', 'RecordedScenarioFields', 'ScenarioModels', 'CooperativeLocalizationDataset', 'load_datasets',
           'load_scenario', 'MRCLAM', 'MRCLAMScenario', 'fitted_scenario',
           'range_part', 'MRCLAMSequence', 'read_mrclam',
           'mrclam_realization', 'integrate_odometry', 'interpolate_pose',
           'fit_models', 'long_run_factor', 'FIT_HORIZON', 'PARTS',
           'sequence_source', 'MRCLAM_URL', 'Recording', 'RangeCalibration',
           'recording_realization', 'recording_report', 'BagTopics',
           'TIERS_TOPICS', 'read_bag', 'RecordingScenario',
           'RecordingDataset', 'fit_range_models',
           'fitted_recording_scenario', 'READERS', 'RECORDING_PARTS',
           'UWB_FIT_HORIZON', 'read_miluv', 'miluv_experiments',
           'READ_COUNTS', 'BIN_COUNTS', 'RANGE_TYPES', 'MIN_SIGMA',
           'UWB_MIN_NU', 'step_of', 'merge_links', 'Links', 'MERGES']
