"""Deprecated import path of :mod:`agents.training.pretrain` (kept for one release; importing it warns)."""

from __future__ import annotations

import warnings

from agents.training.pretrain import (
    ACTION_LOSSES,
    PretrainConfig,
    TeacherData,
    collect_teacher,
    concatenate,
    discounted_returns,
    fit_policy,
    make_teacher,
    pretrain,
    student_policy,
    teacher_class,
    teacher_seeds,
)

__all__ = [
    "ACTION_LOSSES",
    "PretrainConfig",
    "TeacherData",
    "collect_teacher",
    "concatenate",
    "discounted_returns",
    "fit_policy",
    "make_teacher",
    "pretrain",
    "student_policy",
    "teacher_class",
    "teacher_seeds",
]

warnings.warn(
    "agents.pretrain is deprecated and will be removed in the next release: import from agents.training.pretrain",
    DeprecationWarning,
    stacklevel=2,
)
