"""ETH/UCY data layer: recordings, leave-one-out splits, windows, normalisation."""

from crowdnav_mesrnn.data.checks import CheckReport, check_data_dir
from crowdnav_mesrnn.data.constants import (
    BIWI_ETH_DT_S,
    ETH_UCY_DT_S,
    EXPECTED_TEST_WINDOWS,
    OBS_LEN,
    PARTS,
    PRED_LEN,
    RECORDINGS,
    SEQ_LEN,
    SPLIT_TEST_RECORDINGS,
    SPLITS,
    STEP_S,
    TRAIN_ONLY_RECORDINGS,
    check_split,
    split_recordings,
)
from crowdnav_mesrnn.data.normalization import MinMax
from crowdnav_mesrnn.data.paths import ENV_VAR, HOW_TO_GET_DATA, DataNotFoundError, data_available, find_data_dir
from crowdnav_mesrnn.data.recordings import DataFormatError, Recording, load_recording, load_split, parse_file
from crowdnav_mesrnn.data.windows import Window, all_positions, collate, split_windows, windows_from_recording

__all__ = [
    "BIWI_ETH_DT_S",
    "ENV_VAR",
    "ETH_UCY_DT_S",
    "EXPECTED_TEST_WINDOWS",
    "HOW_TO_GET_DATA",
    "OBS_LEN",
    "PARTS",
    "PRED_LEN",
    "RECORDINGS",
    "SEQ_LEN",
    "SPLITS",
    "SPLIT_TEST_RECORDINGS",
    "STEP_S",
    "TRAIN_ONLY_RECORDINGS",
    "CheckReport",
    "DataFormatError",
    "DataNotFoundError",
    "MinMax",
    "Recording",
    "Window",
    "all_positions",
    "check_data_dir",
    "check_split",
    "collate",
    "data_available",
    "find_data_dir",
    "load_recording",
    "load_split",
    "parse_file",
    "split_recordings",
    "split_windows",
    "windows_from_recording",
]
