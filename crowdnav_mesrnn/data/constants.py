"""Typed facts about the ETH/UCY recordings and the standard leave-one-out protocol."""

from __future__ import annotations

from typing import Final

#: Seconds between two annotations in every recording but ``biwi_eth`` (25 fps video, every 10th frame).
ETH_UCY_DT_S: Final[float] = 0.4
#: Seconds between two annotations of ``biwi_eth`` (15 fps video, every 10th frame).
BIWI_ETH_DT_S: Final[float] = 10.0 / 15.0
#: Frame numbers advance by this much between consecutive annotations.
FRAME_STEP: Final[int] = 10

OBS_LEN: Final[int] = 8
"""Observed annotation steps per window (3.2 s at 0.4 s/step)."""
PRED_LEN: Final[int] = 12
"""Predicted annotation steps per window (4.8 s at 0.4 s/step)."""
SEQ_LEN: Final[int] = OBS_LEN + PRED_LEN

#: Recording name -> scene label. Names are the file stems in ``all_data/``.
RECORDINGS: Final[dict[str, str]] = {
    "biwi_eth": "eth",
    "biwi_hotel": "hotel",
    "crowds_zara01": "zara1",
    "crowds_zara02": "zara2",
    "crowds_zara03": "zara3",
    "students001": "univ",
    "students003": "univ",
    "uni_examples": "univ",
}

#: Recording name -> seconds per annotation step.
STEP_S: Final[dict[str, float]] = {name: (BIWI_ETH_DT_S if name == "biwi_eth" else ETH_UCY_DT_S) for name in RECORDINGS}

#: The five leave-one-out splits; the value is the list of whole recordings tested on.
SPLIT_TEST_RECORDINGS: Final[dict[str, tuple[str, ...]]] = {
    "eth": ("biwi_eth",),
    "hotel": ("biwi_hotel",),
    "univ": ("students001", "students003"),
    "zara1": ("crowds_zara01",),
    "zara2": ("crowds_zara02",),
}
SPLITS: Final[tuple[str, ...]] = tuple(SPLIT_TEST_RECORDINGS)
PARTS: Final[tuple[str, ...]] = ("train", "val", "test")

#: Recordings only ever used for training/validation, never as a test scene.
TRAIN_ONLY_RECORDINGS: Final[tuple[str, ...]] = ("crowds_zara03", "uni_examples")

#: Test windows with at least two scored pedestrians under the standard protocol (README of the data).
EXPECTED_TEST_WINDOWS: Final[dict[str, int]] = {
    "eth": 70,
    "hotel": 301,
    "univ": 947,
    "zara1": 602,
    "zara2": 921,
}


def split_recordings(split: str, part: str) -> list[tuple[str, str]]:
    """Files making up one part of a leave-one-out split.

    Returns:
        ``(recording_name, subfolder)`` pairs, where the file is ``<subfolder>/<name><suffix>.txt``
        with suffix ``""`` for ``all_data`` and ``"_train"``/``"_val"`` for the pieces.
    """
    check_split(split)
    if part not in PARTS:
        raise ValueError(f"unknown part {part!r}; valid parts: {', '.join(PARTS)}")
    held_out = SPLIT_TEST_RECORDINGS[split]
    if part == "test":
        return [(name, "all_data") for name in held_out]
    return [(name, part) for name in RECORDINGS if name not in held_out]


def check_split(split: str) -> str:
    """Raise a ``ValueError`` listing the valid splits if ``split`` is not one of them."""
    if split not in SPLIT_TEST_RECORDINGS:
        raise ValueError(f"unknown split {split!r}; valid splits: {', '.join(SPLITS)}")
    return split
